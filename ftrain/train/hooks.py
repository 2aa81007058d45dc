"""Hook protocol and the built-in hooks (console line, TensorBoard, CSV metrics).

A hook is any object derived from :class:`Hook`; it may carry state (``state_dict``/``load_state_dict``) that the
checkpoint saves from rank 0 and restores on every rank. Hooks run on every rank: ``trainer.info.is_main`` tells
rank 0. ``every`` thins out ``after_iteration`` (called when the completed iteration count is a multiple of it).
User hooks come from the config: ``hooks: [{target: "package.module:Class", every: 10, kwargs: {...}}]``.
"""

from __future__ import annotations

import collections
import contextlib
import csv
import importlib
import inspect
import io
import math
import os
import re
import statistics
import time
import typing
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from ftrain.ckpt.format import human_size, step_dir, unloadable_part
from ftrain.config import local_path
from ftrain.errors import UserError, command, error_line, module_missing

METRICS_CSV = "metrics.csv"
"""What ``CsvHook`` writes in the log directory, and ``read_metrics`` reads."""


def metrics_rows(data: bytes) -> csv.DictReader:
    """The rows of a ``metrics.csv`` as its readers take it, damage and all: NUL bytes (a power loss) dropped, bytes
    that are not UTF-8 read as U+FFFD, which marks their row ``damaged``."""
    return csv.DictReader(io.StringIO(data.decode(errors="replace").replace("\0", ""), newline=""))


def damaged(row: dict) -> bool:
    """A row cut short or run together (more or fewer fields than the header), with bytes that were not text, or
    whose iteration, or step resumed from, is not a whole number."""
    if None in row or None in row.values() or any("\ufffd" in value for value in row.values()):
        return True
    numbers = [row.get("iteration") or "", *filter(None, [row.get("resumed_from")])]
    return not all(re.fullmatch(r"[0-9]{1,18}", text) for text in numbers)  # 18 digits: what int() always takes


if TYPE_CHECKING:
    from ftrain.ckpt.manager import Checkpointer
    from ftrain.comm.collectives import Comm
    from ftrain.comm.group import RankInfo
    from ftrain.config import Config
    from ftrain.heartbeat import HeartbeatWriter
    from ftrain.train.envs import MujocoVecEnv


class TrainerView(Protocol):
    """What a hook sees of the training loop (``ftrain.train.trainer.Trainer`` is one): the run's config and ranks,
    the iteration just completed, and the parts the built-in hooks read."""

    config: Config
    info: RankInfo
    iteration: int
    env: MujocoVecEnv
    alg: Any
    """rsl-rl's algorithm (``ftrain.train.ppo.FusedPPO``, or rsl-rl's Distillation)."""
    comm: Comm
    heartbeat: HeartbeatWriter
    checkpointer: Checkpointer
    run_description: dict

    def log(self, message: str, every_rank: bool = False) -> None: ...

    def learned_digest(self) -> str: ...

    def common_state(self) -> dict: ...

    def rank_state(self) -> dict: ...


class Hook:
    """Override the hook points you need; all default to doing nothing."""

    every: int = 1

    def on_start(self, trainer: TrainerView) -> None:
        """After set-up and resume, before the first iteration of this process."""

    def after_rollout(self, trainer: TrainerView) -> None:
        """After the rollout and the return computation of an iteration."""

    def after_update(self, trainer: TrainerView, losses: dict[str, float]) -> None:
        """After the policy update of an iteration."""

    def after_iteration(self, trainer: TrainerView, metrics: dict[str, float]) -> None:
        """After an iteration; ``metrics`` are global (averaged over ranks where it matters)."""

    def on_checkpoint(self, trainer: TrainerView, step: int, manifest: dict) -> None:
        """On every rank, on the main thread, once all ranks agree that checkpoint ``step`` was committed."""

    def on_end(self, trainer: TrainerView) -> None:
        """After the last iteration of this process (completed or preempted)."""

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        """Restore what ``state_dict`` returned."""


class Hooks:
    """The ordered hooks of a run; ``call`` dispatches one hook point to all of them. A hook of the config that
    implements a point inside an iteration runs in a heartbeat phase of its own that names it: the supervisor times
    it apart, and a hang in it names the hook (ours beat their own phases where they take time)."""

    TIMED_POINTS = ("after_rollout", "after_update", "after_iteration")

    def __init__(self, builtin: list[Hook], user: list[Hook] = ()) -> None:
        self.hooks = [*builtin, *user]
        self.user = list(user)
        self._timed = {
            (id(hook), point)
            for hook in user
            for point in self.TIMED_POINTS
            if getattr(type(hook), point) is not getattr(Hook, point)
        }
        """(hook, point) that run in a heartbeat phase of their own: a hook of the config implementing the point."""

    def call(self, point: str, trainer: TrainerView, *args: object) -> None:
        for hook in self.hooks:
            if point == "after_iteration" and trainer.iteration % max(1, hook.every):
                continue
            named = (id(hook), point) in self._timed
            with (
                trainer.heartbeat.running_hook(f"{point} of {_class_name(hook)}", trainer.iteration)
                if named
                else contextlib.nullcontext()
            ):
                getattr(hook, point)(trainer, *args)

    def state_dict(self) -> dict:
        return {key: hook.state_dict() for key, hook in self._keyed()}

    def load_state_dict(self, state: dict) -> None:
        for key, hook in self._keyed():
            if key in state:
                hook.load_state_dict(state[key])

    def check_state(self) -> None:
        """UserError naming the first hook of the config whose state a checkpoint cannot hold as data: asked before
        the first iteration, since the first save, which refuses it too, would throw away the iterations before it."""
        for hook in self.user:
            state = hook.state_dict()
            part = unloadable_part({"state": state})
            if part is not None:
                where = part.removeprefix("state/") if part.startswith("state/") else f"a {type(state).__name__}"
                raise UserError(
                    f"hook {_class_name(hook)}: its state_dict() holds what a checkpoint cannot keep as data ({where}):"
                    " keep tensors, numbers, strings, lists and dicts in it"
                )

    def _keyed(self) -> list[tuple[str, Hook]]:
        """Each hook's key in a checkpoint: its class and its rank among hooks of that class, so turning a built-in
        hook on or off between runs does not hand one hook's state to another."""
        seen: collections.Counter[str] = collections.Counter()
        keyed = []
        for hook in self.hooks:
            name = _class_name(hook)
            keyed.append((f"{name}#{seen[name]}", hook))
            seen[name] += 1
        return keyed


def _class_name(hook: Hook) -> str:
    return f"{type(hook).__module__}.{type(hook).__qualname__}"


class ConsoleHook(Hook):
    """One line per iteration on rank 0: progress, throughput, returns (and the evaluation's, when there is one),
    losses, learning rate, how long ago the newest save committed, ETA; a short line (step, where, size, seconds) for
    the saves a person wants to see: the first of the process, the first past each quarter of the run, the last
    (``every_save``: each; a failed save, a recovery and a hold have lines of their own from the checkpointer); at
    the end, where the run is and how to play or export it (``lines=False``, ``log.console=false``: that alone).

    The ETA is the remaining iterations times the median wall time of the last ``ETA_WINDOW`` iterations of this
    process, not counting the first ``ETA_SKIP`` after a (re)start (imports, the first save, warm caches); until
    there are enough, the iteration's own compute time stands in. A median, not a mean: one stalled iteration (a
    save held through an outage, a paused process) would raise a mean for a whole window, by the stall over the
    window per iteration left; a lasting change of pace moves the median within half a window.
    """

    ETA_WINDOW = 20
    ETA_SKIP = 2
    MILESTONES = 4

    def __init__(
        self, clock: Callable[[], float] = time.perf_counter, every_save: bool = False, lines: bool = True
    ) -> None:
        self.clock = clock
        self.every_save = every_save
        self.lines = lines
        self._saved: tuple[int, float] | None = None
        """The newest committed step this process saw, and when."""
        self._last: float | None = None
        self._intervals = 0
        self._recent: collections.deque[float] = collections.deque(maxlen=self.ETA_WINDOW)
        self._said_no_episode = False

    def after_iteration(self, trainer: TrainerView, metrics: dict[str, float]) -> None:
        if not trainer.info.is_main or not self.lines:
            return
        returned, length = f"{metrics['mean_return']:.2f}", f"{metrics['mean_length']:.0f}"
        if not math.isfinite(metrics["mean_return"]):
            if not self._said_no_episode:
                self._said_no_episode = True
                print(
                    "[ftrain] no episode has finished yet: return and len show rank 0's episodes under way (~) until "
                    "one has",
                    flush=True,
                )
            running = trainer.env.running_episodes()
            returned, length = f"~{running[0]:.2f}", f"~{running[1]:.0f}"
        total = trainer.config.iterations
        eta = _duration((total - trainer.iteration) * self.seconds_per_iteration(metrics["iteration_time"]))
        losses = " ".join(f"{k.removeprefix('loss/')} {v:.3g}" for k, v in metrics.items() if k.startswith("loss/"))
        evaluated = metrics.get("eval_return", math.nan)
        print(
            f"it {trainer.iteration}/{total} | {metrics['steps_per_s']:,.0f} steps/s"
            f" | return {returned} | len {length}"
            f"{f' | eval {evaluated:.2f}' if math.isfinite(evaluated) else ''}"
            f" | {losses} | lr {metrics['learning_rate']:.2e}"
            f"{f' | saved {_duration(self.clock() - self._saved[1])} ago' if self._saved else ''} | ETA {eta}",
            flush=True,
        )

    def on_checkpoint(self, trainer: TrainerView, step: int, manifest: dict) -> None:
        if not trainer.info.is_main:
            return
        previous, self._saved = self._saved, (step, self.clock())
        quarter = max(1, trainer.config.iterations // self.MILESTONES)
        milestone = previous is None or step // quarter > previous[0] // quarter or step >= trainer.config.iterations
        if self.lines and (self.every_save or milestone):
            checkpointer = trainer.checkpointer
            size = human_size(sum(entry["size"] for entry in manifest["files"].values()))
            where = checkpointer.storage.where(step_dir(step))
            print(f"[ftrain] saved step {step} to {where} ({size}, {checkpointer.last_commit_s:.1f} s)", flush=True)

    def on_end(self, trainer: TrainerView) -> None:
        """Where the run is, for whoever comes back to it: storage, newest step, logs, and the commands to use it."""
        if not trainer.info.is_main:
            return
        storage, step = trainer.checkpointer.storage.url, trainer.checkpointer.committed_step
        shows_options = bool(trainer.config.storage.options) and not local_path(storage)  # a local path takes none
        print(
            f"[ftrain] run saved in {storage}: newest step {step if step is not None else '- (none committed)'}; "
            f"logs in {trainer.config.log_dir}\n"
            f"[ftrain] play it: {command('ftrain', 'play', storage)}   export it: "
            f"{command('ftrain', 'export', storage, '--format', 'onnx')}"
            f"{'   (with the storage options of this run: --storage-option KEY=VALUE)' if shows_options else ''}",
            flush=True,
        )

    def seconds_per_iteration(self, compute_time: float) -> float:
        """Record this iteration's end; the estimate of an iteration's wall time (see the class docstring)."""
        now = self.clock()
        if self._last is not None:
            self._intervals += 1
            if self._intervals > self.ETA_SKIP:
                self._recent.append((now - self._last) / max(1, self.every))
        self._last = now
        return statistics.median(self._recent) if len(self._recent) >= self.ETA_SKIP + 1 else compute_time


class TensorBoardHook(Hook):
    """Scalars under ``<log_dir>/tensorboard`` on rank 0, indexed by iteration."""

    def __init__(self) -> None:
        self.writer = None

    def on_start(self, trainer: TrainerView) -> None:
        if trainer.info.is_main:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(  # purge_step: a resumed run's redone iterations replace the old points
                log_dir=str(Path(trainer.config.log_dir) / "tensorboard"),
                flush_secs=10,
                purge_step=trainer.iteration + 1,
            )

    def after_iteration(self, trainer: TrainerView, metrics: dict[str, float]) -> None:
        if self.writer is not None:
            for key, value in metrics.items():
                self.writer.add_scalar(key, value, trainer.iteration)

    def on_end(self, trainer: TrainerView) -> None:
        if self.writer is not None:
            self.writer.close()


class CsvHook(Hook):
    """``<log_dir>/metrics.csv`` on rank 0, one row per iteration: a resumed run first drops the rows past the step
    it resumed from (the iterations it is about to redo), then appends; its first row names that step in
    ``resumed_from`` (empty in every other row), and ``config_change`` what changed there and was let through."""

    def __init__(self) -> None:
        self.file = None
        self.writer: csv.DictWriter | None = None
        self.resumed_from: int | None = None
        self.config_change: str | None = None

    def on_start(self, trainer: TrainerView) -> None:
        self.resumed_from = trainer.iteration or None
        self.config_change = trainer.checkpointer.config_change

    def after_iteration(self, trainer: TrainerView, metrics: dict[str, float]) -> None:
        if not trainer.info.is_main:
            return
        if self.writer is None:
            self._open(Path(trainer.config.log_dir) / METRICS_CSV, trainer.iteration - 1, metrics, trainer.log)
        resume = {"resumed_from": self.resumed_from or "", "config_change": self.config_change or ""}
        self.writer.writerow({"iteration": trainer.iteration, **metrics, **resume})
        self.resumed_from = self.config_change = None
        self.file.flush()

    def _open(self, path: Path, kept: int, metrics: dict[str, float], log: Callable[[str], None]) -> None:
        """Open ``path`` to append: rows past iteration ``kept`` go (a resumed run redoes them), and a file of an
        older version gains the columns it lacks. Damage never stops a run: rows cut short (a crash, a power loss's
        NUL bytes) or holding bytes that are not text are dropped, and a file that is not a metrics CSV is set aside
        (``.unreadable``) for a new one."""
        fields: list[str] = []
        rows: list[dict] = []
        if path.exists() and path.stat().st_size:
            try:
                reader = metrics_rows(path.read_bytes())
                fields = list(reader.fieldnames or [])
                if "iteration" not in fields:
                    raise ValueError("it has no iteration column")
                whole = (row for row in reader if not damaged(row))
                rows = [row for row in whole if int(row["iteration"]) <= kept]
            except (ValueError, csv.Error) as error:
                aside = path.with_name(f"{path.name}.unreadable")
                os.replace(path, aside)
                log(f"{path} is not a metrics CSV ({error}): set aside as {aside.name}; a new one starts here")
                fields, rows = [], []
        fields += [name for name in ["iteration", *metrics, *CSV_ONLY[1:]] if name not in fields]
        tmp = path.with_suffix(".csv.tmp")
        with tmp.open("w", newline="") as file:
            writer = csv.DictWriter(file, fields)
            writer.writeheader()
            writer.writerows(rows)
        os.replace(tmp, path)
        self.file = path.open("a", newline="")
        self.writer = csv.DictWriter(self.file, fields, extrasaction="ignore")

    def on_end(self, trainer: TrainerView) -> None:
        if self.file is not None:
            self.file.close()


def read_metrics(log_dir: str, after: int, until: int) -> list[tuple[int, dict[str, float]]]:
    """The rows ``CsvHook`` wrote for iterations ``after`` < i <= ``until``, as (iteration, metrics); a row being
    written, or a file that is not there, yields nothing."""
    path = Path(log_dir) / METRICS_CSV
    if not path.exists():
        return []
    with path.open(newline="") as file:
        rows = list(csv.DictReader(file))
    found = []
    for row in rows:
        try:
            iteration = int(row["iteration"])
            metrics = {key: float(value) for key, value in row.items() if key not in CSV_ONLY and value}
        except (TypeError, ValueError):
            continue
        if after < iteration <= until:
            found.append((iteration, metrics))
    return found


CSV_ONLY = ("iteration", "resumed_from", "config_change")
"""Columns of metrics.csv that are not metrics."""


def hook_target(target: str) -> typing.Callable[..., Hook]:
    """What ``target`` (``module:Class``) names, imported; UserError naming it where it cannot be. A worker asks
    before it takes the storage or says anything (``ftrain train``), so that a hook that does not import is one line
    and leaves nothing behind."""
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except Exception as error:
        if module_missing(error, module_name):
            raise UserError(f"hook target {target!r} cannot be imported ({error}): fix the import path") from None
        # the module itself raised (an import of its own included): the user's code, which a restart would run alike
        raise UserError(f"hook target {target!r} cannot be imported: {error_line(error)}: fix the module") from None
    try:
        return getattr(module, class_name)
    except AttributeError as error:
        raise UserError(f"hook target {target!r} cannot be imported ({error}): fix the import path") from None


def hook_class(target: str, kwargs: dict) -> type[Hook]:
    """The class ``target`` names, a Hook whose constructor takes ``kwargs``; UserError where not. Checked with the
    hook's module (``train.user_code``), before a run takes anything, as it is without making the hook."""
    cls = hook_target(target)
    if not (isinstance(cls, type) and issubclass(cls, Hook)):
        raise UserError(f"hook {target!r} is not a subclass of ftrain.train.hooks.Hook: make it one, or name one")
    try:
        signature = inspect.signature(cls)
    except (TypeError, ValueError):  # a constructor Python cannot look into: making the hook tells
        return cls
    try:
        signature.bind(**kwargs)
    except TypeError as error:
        raise UserError(f"hook {target!r} rejects its kwargs ({error}): fix its kwargs") from None
    return cls


def load_hook(target: str, kwargs: dict) -> Hook:
    cls = hook_class(target, kwargs)
    try:
        return cls(**kwargs)
    except Exception as error:
        raise UserError(f"hook {target!r} cannot be made: {error_line(error)}: fix the hook or its kwargs") from None


def _duration(seconds: float) -> str:
    if not math.isfinite(seconds):
        return "?"
    seconds = int(seconds)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{secs:02d}s"
