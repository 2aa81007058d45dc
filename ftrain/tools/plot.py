"""``ftrain plot``: a run's learning curves as one PNG, with its restarts marked.

Reads ``<run>/metrics.csv`` (the CSV hook's; a resumed run appends and redoes iterations, so the last row of each
iteration wins) and, if the supervisor ran, ``<run>/events.jsonl``. A restart is drawn at the checkpoint step the
run resumed from: from the supervisor's ``resumed`` events, and wherever the iterations in metrics.csv go back.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

from ftrain.errors import UserError

METRICS = "metrics.csv"
EVENTS = "events.jsonl"


@dataclass
class Plot:
    path: Path
    panels: list[str]
    """The titles of the panels drawn."""
    restarts: list[int]
    """The steps at which restarts are marked."""


def read_metrics(run: Path) -> tuple[dict[str, list[float]], list[int]]:
    """Columns by name, ordered by iteration (the last row of each iteration wins), and the restarts seen in the
    file: the step resumed from wherever the iteration goes back."""
    path = run / METRICS
    if not path.is_file():
        raise UserError(f"{path} does not exist: pass a run's log directory (where training wrote {METRICS})")
    rows: dict[int, dict[str, str]] = {}
    restarts: set[int] = set()
    previous = 0
    with path.open(newline="") as file:
        for row in csv.DictReader(file):
            iteration = int(row["iteration"])
            if iteration <= previous:
                restarts.add(iteration - 1)
            previous = iteration
            rows[iteration] = row
    if not rows:
        raise UserError(f"{path} has no rows yet: plot the run after its first iteration")
    ordered = [rows[iteration] for iteration in sorted(rows)]
    columns = {name: [_number(row.get(name)) for row in ordered] for name in ordered[-1]}
    return columns, sorted(restarts)


def read_restarts(run: Path) -> list[int]:
    """Steps the supervisor's workers resumed from (``resumed`` events; a fresh start has no step)."""
    path = run / EVENTS
    if not path.is_file():
        return []
    steps = set()
    for line in path.read_text().splitlines():
        try:
            event = json.loads(line)
        except json.JSONDecodeError:
            continue  # a line cut short by a crash of the supervisor itself
        if event.get("event") == "resumed" and isinstance(event.get("step"), int):
            steps.add(event["step"])
    return sorted(steps)


def plot_run(run: str | Path, output: str | Path | None = None) -> Plot:
    """Write the learning curves of the run whose log directory is ``run`` to ``output`` (default
    ``<run>/curves.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    run = Path(run)
    columns, restarts = read_metrics(run)
    restarts = sorted(set(restarts) | set(read_restarts(run)))
    iterations = columns.pop("iteration")
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
            {name: name.removeprefix("loss/") for name in columns if name.startswith("loss/")},
        ),
        ("Throughput", "environment steps / s", {"steps_per_s": "all ranks"}),
    ]
    panels = [(title, unit, {k: v for k, v in series.items() if k in columns}) for title, unit, series in panels]
    panels = [panel for panel in panels if panel[2]]
    figure, axes = plt.subplots(2, 2, figsize=(12, 8), squeeze=False)
    for ax, (title, unit, series) in zip(axes.flat, panels, strict=False):
        for name, label in series.items():
            values = columns[name]
            points = [(x, y) for x, y in zip(iterations, values, strict=True) if not math.isnan(y)]
            style = "o-" if name == "eval_return" else "-"
            ax.plot([x for x, _ in points], [y for _, y in points], style, label=label, markersize=3)
        if title == "Losses":
            ax.set_yscale("symlog", linthresh=1e-2)
        for index, step in enumerate(restarts):
            ax.axvline(step, color="tab:red", linestyle="--", linewidth=1, label="restart" if index == 0 else None)
        ax.set_title(title)
        ax.set_xlabel("iteration")
        ax.set_ylabel(unit)
        ax.grid(alpha=0.3)
        ax.legend(fontsize="small")
    for ax in axes.flat[len(panels) :]:
        ax.set_visible(False)
    marked = f", {len(restarts)} restart{'s' * (len(restarts) != 1)} (dashed: step resumed from)" if restarts else ""
    figure.suptitle(f"{run.resolve().name}: {int(iterations[-1])} iterations{marked}")
    figure.tight_layout()
    path = Path(output) if output else run / "curves.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    plt.close(figure)
    print(f"wrote {path}")
    return Plot(path, [title for title, _, _ in panels], restarts)


def _number(text: str | None) -> float:
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan
