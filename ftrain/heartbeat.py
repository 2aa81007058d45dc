"""Heartbeat files: how workers tell the supervisor they are alive, and where they are.

Each rank rewrites ``<dir>/rank-<L>.json`` (L: its local rank, so that the workers torchrun restarts in a world of
another size replace their predecessors' files) atomically (temp file + rename, a local directory only) whenever
its phase changes. The supervisor reads them without importing torch. Fields:

- ``rank``, ``pid``: who wrote it (its global rank).
- ``iteration``: iterations completed when the phase began.
- ``phase``: a ``Phase``: ``start`` (resumed or fresh, before the first iteration), ``rollout``, ``update``,
  ``evaluate``, ``snapshot``, ``hook``, ``checkpoint``, ``closing``, ``done`` (all iterations finished),
  ``preempted`` (saved on request, exiting).
- ``hook``: in phase ``hook``, which hook of the config runs, and where (``after_iteration of pkg.mod.Class``).
- ``committed_step``: the newest checkpoint step this run has committed or resumed from (None if none).
- ``resumed_step``: the step this process resumed from (None for a fresh start).
- ``seq``: increases with every write, so a reader sees progress even when the clock does not move.
- ``time``: wall-clock seconds, for humans and hang timing only; nothing trained depends on it.
- ``world``: the world size; ``nodes``: the number of every node in it (see ``NODE_ENV``), sorted.
- ``config_change``: what ``allow_config_change`` let change at the resume (None: nothing).

The other way, ``<dir>/stop`` holds why the supervisor stops the workers, which it does with SIGTERM whatever it got:
a SIGINT passed on as such would reach a warm worker twice (from its stand-in too), and a second SIGINT stops a
worker without a save. So that the workers' last line still names what the user sent (Ctrl-C, say).
"""

from __future__ import annotations

import contextlib
import enum
import json
import os
import signal
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ftrain.files import replace_text

ENV_DIR = "FTRAIN_HEARTBEAT_DIR"
TOKEN_ENV = "FTRAIN_ATTEMPT_TOKEN"
"""Set by the supervisor in every worker's environment: how it finds all processes of an attempt."""
NODE_ENV = "FTRAIN_NODE"
"""Set by the supervisor in every worker's environment: its node's number (``--node-rank``; etcd-v2: taken from etcd),
which the heartbeats list in ``nodes``."""


STOP_FILE = "stop"


def write_stop_reason(directory: str | os.PathLike, received: int) -> None:
    """Before the supervisor SIGTERMs the workers of ``directory``: that it ``received`` this signal. Never raises: a
    full disk costs the workers' line its reason, not the stop."""
    name = signal.Signals(received).name
    reason = f"{name} to the supervisor" + (" (Ctrl-C), passed on as SIGTERM" if name == "SIGINT" else "")
    with contextlib.suppress(OSError):
        replace_text(Path(directory) / STOP_FILE, reason)


def read_stop_reason(directory: str | os.PathLike | None) -> str | None:
    """What ``write_stop_reason`` wrote in ``directory`` (None: no supervisor, or it did not stop the workers)."""
    try:
        return (Path(directory) / STOP_FILE).read_text() or None if directory else None
    except OSError:
        return None


class Phase(enum.StrEnum):
    """What a rank is doing; the supervisor times each phase on its own (``supervise/hang.py``)."""

    START = "start"
    ROLLOUT = "rollout"
    UPDATE = "update"
    EVALUATE = "evaluate"
    SNAPSHOT = "snapshot"
    """Rank 0 exports a policy snapshot (an ONNX export takes seconds)."""
    HOOK = "hook"
    """A hook of the config runs inside an iteration (``Heartbeat.hook`` names it): timed on its own, so that one
    that hangs is named, and its slow work does not widen the limit of the phase it interrupts."""
    CHECKPOINT = "checkpoint"
    CLOSING = "closing"
    """The end of an attempt (the last iteration, or a stop): its save held until committed, the writer closed, the
    hooks' ``on_end`` (trackers flushing). Limited by the start-up grace alone (``hang.UNTIMED_PHASES``): a slow close
    on rank 0 is no hang, after saves of 0.1 s or beside a peer that closed at once."""
    DONE = "done"
    PREEMPTED = "preempted"


@dataclass
class Heartbeat:
    rank: int
    pid: int
    iteration: int
    phase: Phase
    committed_step: int | None
    resumed_step: int | None
    seq: int
    time: float
    world: int = 1
    nodes: list[int] = field(default_factory=list)
    config_change: str | None = None
    """What ``allow_config_change`` let change at the resume (``ftrain.ckpt.changes``), for the ``resumed`` event."""
    longest: dict[str, float] = field(default_factory=dict)
    """Phase -> the longest this process has spent in it, on its own clock, past start-up and its first iteration:
    what the supervisor's hang limits are made of, whether or not one of its polls happened to see the phase (a
    phase of milliseconds seldom meets a poll a tenth of a second apart)."""
    hook: str | None = None
    """In phase ``hook``: the hook point and the hook's class (``after_iteration of pkg.mod.Class``)."""


class HeartbeatWriter:
    """Writes this rank's heartbeat; a no-op when no directory is configured."""

    def __init__(
        self,
        directory: str | os.PathLike | None,
        rank: int,
        local_rank: int | None = None,
        world: int = 1,
        nodes: list[int] = (),
    ) -> None:
        slot = rank if local_rank is None else local_rank
        self.path = Path(directory) / f"rank-{slot}.json" if directory else None
        self.rank = rank
        self.world = world
        self.nodes = sorted(set(nodes))
        self.seq = 0
        self.iteration = 0
        self.committed_step: int | None = None
        self.resumed_step: int | None = None
        self.config_change: str | None = None
        self.longest: dict[str, float] = {}
        self.phase = Phase.START
        self._hook: str | None = None
        self._timing: tuple[Phase, float] | None = None
        """The phase being timed and when it began (None: start-up or the first iteration, not timed)."""
        self._first: int | None = None
        """The iteration of the first heartbeat past start-up."""
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)

    def beat(self, phase: Phase, iteration: int | None = None) -> None:
        if iteration is not None:
            self.iteration = iteration
        self.phase = Phase(phase)
        if self.path is None:
            return
        now = time.monotonic()
        if self._timing is not None:
            timed, since = self._timing
            self.longest[timed] = max(self.longest.get(timed, 0.0), now - since)
        if phase != Phase.START and self._first is None:
            self._first = self.iteration
        past_first = phase != Phase.START and self.iteration > self._first
        self._timing = (phase, now) if past_first else None
        self.seq += 1
        beat = Heartbeat(
            self.rank,
            os.getpid(),
            self.iteration,
            phase,
            self.committed_step,
            self.resumed_step,
            self.seq,
            time.time(),
            self.world,
            self.nodes,
            self.config_change,
            {str(timed): round(seconds, 4) for timed, seconds in self.longest.items()},
            self._hook if phase == Phase.HOOK else None,
        )
        replace_text(self.path, json.dumps(asdict(beat)))

    @contextlib.contextmanager
    def running_hook(self, name: str, iteration: int) -> Iterator[None]:
        """Phase ``hook`` naming ``name`` while the block runs, then the phase it interrupted again. ``iteration``:
        the iterations completed, one more than the interrupted phase's in ``after_iteration``: a hook that fails
        there loses that iteration, and the supervisor counts it lost."""
        interrupted, self._hook = self.phase, name
        self.beat(Phase.HOOK, iteration)
        try:
            yield
        finally:
            self._hook = None
            self.beat(interrupted)


def read_heartbeats(directory: str | os.PathLike) -> dict[int, Heartbeat]:
    """Every rank's latest heartbeat in ``directory`` (unreadable or half-written files are skipped)."""
    beats: dict[int, Heartbeat] = {}
    for path in Path(directory).glob("rank-*.json"):
        try:
            beat = Heartbeat(**json.loads(path.read_text()))
            beat.phase = Phase(beat.phase)
        except (OSError, ValueError, TypeError):
            continue
        beats[beat.rank] = beat
    return beats
