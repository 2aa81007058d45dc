"""``ftrain plot``: a run's learning curves as one PNG, with its restarts and resumes marked.

Reads, from a local directory or any fsspec URL (a log directory copied to S3, say), ``<run>/metrics.csv`` (the CSV
hook's: one row per iteration, the first row after a resume names the step in ``resumed_from``; in files of older
ftrain versions an iteration redone appears twice, and its last row wins) and, if the supervisor ran,
``<run>/events.jsonl``. Restarts are counted as the supervisor counts them: each ``restart`` event, drawn at the step
the next attempt resumed from. Every other resume (the same command run again after a
preemption or by hand) is a resume, and one that ``allow_config_change=true`` let through with a changed config
(``config_change`` in its row) is a config change. A run's storage URL on S3 or elsewhere, which holds no
``metrics.csv``, is plotted from its default log directory on this machine (``runs/<name>/<protocol>/...``).
"""

from __future__ import annotations

import csv
import glob
import itertools
import json
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from ftrain.ckpt.format import parse_checkpoint_url
from ftrain.ckpt.steps import check_output
from ftrain.ckpt.storage import Storage
from ftrain.config import default_log_dir, expand_home
from ftrain.errors import UserError, counted
from ftrain.train.hooks import damaged, metrics_rows
from ftrain.values import is_whole

METRICS = "metrics.csv"
EVENTS = "events.jsonl"
NOT_OURS = "pass a run's log directory, with the files ftrain wrote there"
"""The fix for a metrics file that ftrain cannot have written (no iteration column, no row that is whole)."""


@dataclass
class Plot:
    path: Path
    title: str
    """The figure's title: the run's name, its iterations, and what the marks mean."""
    panels: list[str]
    """The titles of the panels drawn."""
    restarts: list[int]
    """The supervisor's restarts, each at the step it resumed from (twice a step that two resumed from)."""
    resumes: list[int]
    """The steps of the other resumes."""
    changes: list[int]
    """The steps resumed from with a changed config (``allow_config_change=true``)."""
    missing: list[tuple[int, int]]
    """The iterations (first, last) that ``metrics.csv`` has no rows for (a start with ``log.csv=false``, rows lost):
    the curves break there rather than draw a line across."""


def _logs_here(storage: Storage) -> str:
    """The log directory of the run on remote ``storage`` (which holds no ``metrics.csv``: its logs stay on the
    machine that trained it), where one run logged it by default under this directory (``runs/<name>/<protocol>/
    <bucket>/<prefix>``); else UserError saying where to look."""
    pattern = glob.escape(default_log_dir(storage.url, "\0")).replace("\0", "*")
    found = sorted(path for path in glob.glob(pattern) if (Path(path) / METRICS).is_file())
    if len(found) == 1:
        return found[0]
    missing = f"{storage.where(METRICS)} does not exist"
    if found:
        raise UserError(f"{missing}, and several runs here logged that storage: {', '.join(found)}: pass one")
    raise UserError(
        f"{missing}: a run on this storage logs to {default_log_dir(storage.url, '<name>')} under the directory it "
        "was started in, on the machine that trained it: pass that directory"
    )


def read_metrics(
    run: str | Path, options: dict | None = None
) -> tuple[dict[str, list[float]], list[int], dict[int, str]]:
    """Columns by name, ordered by iteration (the last row of each iteration wins), the steps resumed from (the
    ``resumed_from`` column, and wherever the iterations go back: files of older versions), and those of them resumed
    with a changed config, with what changed. ``options``: fsspec storage options."""
    storage = Storage.open(str(run), options)
    path = storage.where(METRICS)
    data = _read(storage, METRICS)
    if data is None:
        raise UserError(f"{path} does not exist: pass a run's log directory (where training wrote {METRICS})")
    rows: dict[int, dict[str, str]] = {}
    restarts: set[int] = set()
    changes: dict[int, str] = {}
    previous, skipped = 0, []
    reader = metrics_rows(data)
    try:
        if reader.fieldnames is not None and "iteration" not in reader.fieldnames:
            raise UserError(f"{path} has no iteration column (its columns: {', '.join(reader.fieldnames)}): {NOT_OURS}")
        for row in reader:
            if damaged(row):  # as training's own reader of the file drops them (``CsvHook``)
                skipped.append(reader.line_num)  # the line it ends on
                continue
            iteration = int(row["iteration"])  # a whole number: ``damaged`` says so
            if iteration <= previous:
                restarts.add(iteration - 1)
            if row.get("resumed_from"):
                resumed_from = int(row["resumed_from"])
                restarts.add(resumed_from)
                if row.get("config_change"):
                    changes[resumed_from] = row["config_change"]
            previous = iteration
            rows[iteration] = row
    except csv.Error as error:
        raise UserError(f"{path} line {reader.line_num} is not CSV ({error}): {NOT_OURS}") from None
    if not rows and skipped:
        raise UserError(f"{path} holds no row but {counted(len(skipped), 'damaged one')}: {NOT_OURS}")
    if not rows:
        raise UserError(f"{path} has no rows yet: plot the run after its first iteration")
    if skipped:
        print(
            f"ftrain plot: {path}: skipped {counted(len(skipped), 'damaged row')} ({_lines(skipped)})", file=sys.stderr
        )
    ordered = [rows[iteration] for iteration in sorted(rows)]
    columns = {name: [_number(row.get(name)) for row in ordered] for name in ordered[-1] if name != "config_change"}
    return columns, sorted(restarts), changes


def read_restarts(storage: Storage) -> list[int]:
    """The supervisor's restarts, each at the step the attempt after it resumed from (0: from the start)."""
    steps, restarted = [], False
    for line in (_read(storage, EVENTS) or b"").decode(errors="replace").splitlines():
        try:
            event = json.loads(line)
        except (json.JSONDecodeError, RecursionError):
            continue  # a line cut short by a crash of the supervisor itself, or not the supervisor's
        if not isinstance(event, dict):
            continue  # not the supervisor's: a line damaged since
        if event.get("event") == "restart":
            restarted = True
        elif event.get("event") == "resumed" and restarted:
            step = event.get("step")
            steps.append(step if is_whole(step) else 0)
            restarted = False
    return sorted(steps)


def plot_run(run: str | Path, output: str | Path | None = None, options: dict | None = None) -> Plot:
    """Write the learning curves of the run whose log directory is ``run`` to ``output`` (default
    ``<run>/curves.png``; for a run elsewhere than on this machine, ``runs/<its name>/curves.png``). ``options``: fsspec
    storage options."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.backend_bases import FigureCanvasBase

    run = expand_home(str(run))
    if Path(run).name == METRICS and Path(run).is_file():  # the file itself, for the directory that holds it
        run = str(Path(run).parent)
    root, step = parse_checkpoint_url(run)
    if step is not None:  # a step, as play and export take it: its run's curves
        print(f"ftrain plot: {run} is step {step} of {root}: plotting {root}", file=sys.stderr)
        run = root
    if output is not None and (Path(output).is_dir() or str(output).endswith(("/", os.sep))):  # a folder, made
        output = Path(output) / "curves.png"
    elif output is not None and not Path(output).suffix:  # what matplotlib writes, and what is said, named alike
        output = Path(output).with_name(Path(output).name + ".png")
    if output is not None and Path(output).suffix.lstrip(".").lower() not in FigureCanvasBase.get_supported_filetypes():
        raise UserError(f"-o {output}: not a picture file matplotlib writes: end it in .png, .svg or .pdf")
    storage = Storage.open(str(run), options)
    if not storage.is_local and not storage.exists(METRICS):  # a run's storage, not its logs copied there
        run = _logs_here(storage)
        print(f"ftrain plot: the logs of {storage.url} are in {run}", file=sys.stderr)
        storage = Storage.open(run)
    columns, resumed, changed = read_metrics(run, options)
    run_name = Path(run).resolve().name if storage.is_local else PurePosixPath(storage.url).name
    path = Path(output) if output else Path(default_log_dir(str(run), run_name)) / "curves.png"
    check_output(path, "-o")
    changes = sorted(changed)
    restarts = [step for step in read_restarts(storage) if step not in changes]  # two from one step are two
    resumes = sorted(set(resumed) - set(restarts) - set(changes))
    iterations = columns.pop("iteration")
    missing = gaps(iterations)
    if missing:
        spans = ", ".join(f"{first}-{last}" if last > first else f"{first}" for first, last in missing)
        print(
            f"ftrain plot: {storage.where(METRICS)} has no rows for iterations {spans} (logged with log.csv=false, or "
            "lost): the curves break there",
            file=sys.stderr,
        )
    panels = [
        (
            "Episode return",
            "return per episode",
            {"mean_return": "training (sampled actions)", "eval_return": "evaluation (deterministic)"},
        ),
        ("Episode length", "steps per episode", {"mean_length": "training"}),
        (
            "Losses",
            "loss (symmetric log scale)",
            {column: column.removeprefix("loss/") for column in columns if column.startswith("loss/")},
        ),
        ("Throughput", "environment steps / s", {"steps_per_s": "all ranks"}),
    ]
    drawn = {column for column, values in columns.items() if not all(map(math.isnan, values))}
    panels = [(title, unit, {k: v for k, v in series.items() if k in drawn}) for title, unit, series in panels]
    panels = [panel for panel in panels if panel[2]]  # no empty panel: a run too short for an episode to end
    figure, axes = plt.subplots(2, 2, figsize=(12, 8), squeeze=False)
    for ax, (title, unit, series) in zip(axes.flat, panels, strict=False):
        for column, label in series.items():
            xs, ys = curve(iterations, columns[column], missing)
            ax.plot(xs, ys, "o-" if column == "eval_return" else "-", label=label, markersize=3)
        if title == "Losses":
            ax.set_yscale("symlog", linthresh=1e-2)
        for index, step in enumerate(sorted(set(restarts))):
            ax.axvline(step, color="tab:red", linestyle="--", linewidth=1, label="restart" if index == 0 else None)
        for index, step in enumerate(resumes):
            ax.axvline(step, color="tab:gray", linestyle=":", linewidth=1, label="resume" if index == 0 else None)
        for index, step in enumerate(changes):
            label = "config change" if index == 0 else None
            ax.axvline(step, color="tab:orange", linestyle="-.", linewidth=1.5, label=label)
        ax.set_title(title)
        ax.set_xlabel("iteration")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    marks = [counted(len(restarts), "restart") + " (dashed)" if restarts else ""]
    marks.append(counted(len(resumes), "resume") + " (dotted)" if resumes else "")
    marks.append(counted(len(changes), "config change") + " (dash-dot)" if changes else "")
    marked = ", ".join(mark for mark in marks if mark)
    where = f", {marked}: at the step resumed from" if marked else ""
    title = f"{run_name}: {int(iterations[-1])} iterations{where}"
    figure.suptitle(title)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
    print(f"wrote {path}")
    return Plot(path, title, [panel for panel, _, _ in panels], restarts, resumes, changes, missing)


def gaps(iterations: list[float]) -> list[tuple[int, int]]:
    """The runs of iterations (first, last) missing between the first and last of ``iterations`` (sorted)."""
    return [(int(a) + 1, int(b) - 1) for a, b in itertools.pairwise(iterations) if b - a > 1]


def curve(
    iterations: list[float], values: list[float], missing: list[tuple[int, int]]
) -> tuple[list[float], list[float]]:
    """One curve's points: the iterations with a value (an evaluation's column has one every few rows, joined by a
    line), and a NaN at each run of ``missing`` iterations, where matplotlib breaks the line."""
    points = [(x, y) for x, y in zip(iterations, values, strict=True) if not math.isnan(y)]
    points += [(first, math.nan) for first, _ in missing]
    points.sort(key=lambda point: point[0])
    return [x for x, _ in points], [y for _, y in points]


def _read(storage: Storage, name: str) -> bytes | None:
    """The bytes of ``name`` in ``storage``; None if it does not exist."""
    try:
        return storage.read(name)
    except FileNotFoundError:
        return None


def _lines(numbers: list[int], shown: int = 5) -> str:
    """Where in the file, for a reader to look: the first few line numbers."""
    more = f" and {len(numbers) - shown} more" if len(numbers) > shown else ""
    return f"line{'s' * (len(numbers) != 1)} {', '.join(map(str, numbers[:shown]))}{more}"


def _number(text: str | None) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan
