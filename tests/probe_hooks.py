"""Hooks that the training tests load into real runs by import path (``PYTHONPATH=tests``)."""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from pathlib import Path

from ftrain.ckpt import save
from ftrain.comm import group
from ftrain.heartbeat import Phase
from ftrain.train.hooks import Hook


class RankAgreementHook(Hook):
    """After every iteration, gathers each rank's learned-state digest; rank 0 appends them to ``path``."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        digests = group.all_gather_object(trainer.learned_digest(), trainer.info)
        if trainer.info.is_main:
            with self.path.open("a") as file:
                file.write(json.dumps({"iteration": trainer.iteration, "digests": digests}) + "\n")


class CountingHook(Hook):
    """Counts the iterations it has seen; the count is hook state, so it must survive a resume."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)
        self.seen = 0

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        self.seen += 1
        if trainer.info.is_main:
            self.path.write_text(json.dumps({"iteration": trainer.iteration, "seen": self.seen}))

    def state_dict(self) -> dict:
        return {"seen": self.seen}

    def load_state_dict(self, state: dict) -> None:
        self.seen = state["seen"]


class NumpyStateHook(Hook):
    """Keeps a numpy value in its state: saved fine, but not loadable with weights_only, so it must be refused."""

    def __init__(self, path: str) -> None:
        self.path = path

    def state_dict(self) -> dict:
        import numpy as np

        return {"best": np.float64(1.5)}


class UnpicklableStateHook(Hook):
    """Keeps what cannot be pickled at all in its state (a lambda, or a lock): it must be refused as the above;
    ``after``: from that iteration on only, plain data before."""

    def __init__(self, kind: str, after: int = 0) -> None:
        self.kind, self.after, self.done = kind, after, 0

    def after_iteration(self, trainer, metrics: dict) -> None:
        self.done = trainer.iteration

    def state_dict(self) -> dict:
        import threading

        if self.done < self.after:
            return {"kept": None}
        return {"kept": (lambda x: x) if self.kind == "lambda" else threading.Lock()}


class FailingLoadHook(Hook):
    """Saves a state that verifies, but refuses to load it back: a hook changed between runs."""

    def state_dict(self) -> dict:
        return {"version": 1}

    def load_state_dict(self, state: dict) -> None:
        raise ValueError("hook refuses its old state")


class CrashingHook(Hook):
    """Raises on one rank after one iteration, once per run (``path`` remembers it): a bug in a worker."""

    def __init__(self, path: str, rank: int, iteration: int) -> None:
        self.marker = Path(path)
        self.rank = rank
        self.iteration = iteration

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        if trainer.info.rank == self.rank and trainer.iteration == self.iteration and not self.marker.exists():
            self.marker.touch()
            raise RuntimeError(f"probe crash after iteration {self.iteration}")


class PacingHook(Hook):
    """Sleeps after every iteration: a run long enough, in wall time, for nodes to be lost and to come back."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        time.sleep(self.seconds)


class SlowFirstIterationHook(Hook):
    """Sleeps ``seconds`` after the first rollout of a fresh start (not of a resume): a first iteration as slow as a
    large rollout, an evaluation or a first save of a large policy makes it."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds
        self.first = True

    def after_rollout(self, trainer) -> None:
        if self.first and trainer.iteration == 0:
            time.sleep(self.seconds)
        self.first = False


class LingerHook(Hook):
    """Sleeps ``seconds`` after every rollout and update from iteration ``start`` on, in its heartbeat phase ``hook``:
    long enough that a test which polls the heartbeats to kill a run there cannot miss it, however short a smoke
    run's phases are."""

    def __init__(self, seconds: float, start: int) -> None:
        self.seconds, self.start = seconds, start

    def after_rollout(self, trainer) -> None:
        self._linger(trainer)

    def after_update(self, trainer, losses: dict[str, float]) -> None:
        self._linger(trainer)

    def _linger(self, trainer) -> None:
        if trainer.iteration >= self.start:
            time.sleep(self.seconds)


class SlowEndHook(Hook):
    """Sleeps ``seconds`` in rank 0's ``on_end``: the end of a run as slow as a tracker (rank 0's alone) that flushes
    over a slow network, while the other ranks close at once."""

    def __init__(self, seconds: float) -> None:
        self.seconds = seconds

    def on_end(self, trainer) -> None:
        if trainer.info.is_main:
            time.sleep(self.seconds)


class HangOnceHook(Hook):
    """Rank 0 hangs for good in ``after_iteration`` of iteration ``iteration`` of a resumed run, once: it first
    creates ``marker``, which later attempts find. A hook that waits on what never comes (a lock, a socket)."""

    def __init__(self, iteration: int, marker: str) -> None:
        self.iteration, self.marker = iteration, Path(marker)

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        resumed = trainer.heartbeat.resumed_step is not None
        if trainer.info.is_main and resumed and trainer.iteration == self.iteration and not self.marker.exists():
            self.marker.touch()
            time.sleep(3600)


class HoldHook(Hook):
    """Every rank holds after iteration ``iteration`` until the file ``release`` exists; rank 0 first writes its pid
    to ``marker``. A test acts at a known point of a live run (a trap set, intruders refused) however slow the
    machine, and the run spends no CPU meanwhile. The ranks beat while they hold: slow work to a supervisor."""

    def __init__(self, marker: str, release: str, iteration: int) -> None:
        self.marker, self.release, self.iteration = Path(marker), Path(release), iteration

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        if trainer.iteration != self.iteration:
            return
        if trainer.info.is_main:
            self.marker.write_text(str(os.getpid()))
        while not self.release.exists():
            trainer.heartbeat.beat(Phase.UPDATE)
            time.sleep(0.2)


class HoldCommitHook(Hook):
    """Once the file ``arm`` exists, rank 0 of a world of ``world`` ranks holds its next commit where the shards are
    written and gathered and the fence is not yet read (on the checkpoint writer's thread), and its training loop
    holds too, beating (slow work to its supervisor, no hang): it writes its pid to ``marker`` and waits until
    ``release`` exists. The test arms it once the run is where it wants it, then pauses the node or cuts its link at
    once (the other ranks, waiting for rank 0, are called hung after 5 s), and lets it go on once the others went on:
    a commit in flight, exactly."""

    def __init__(self, arm: str, marker: str, release: str, world: int) -> None:
        self.arm, self.marker, self.release, self.world = Path(arm), Path(marker), Path(release), world
        self.holding = threading.Event()

    def on_start(self, trainer) -> None:
        if not trainer.info.is_main or trainer.info.world_size != self.world:
            return
        commit = save.commit  # what writes the manifest: its write runs the fence's check

        def held(*args, **kwargs) -> dict:
            if self.arm.exists() and not self.release.exists():
                self.holding.set()
                while not self.release.exists():
                    time.sleep(0.05)
            return commit(*args, **kwargs)

        save.commit = held

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        if not self.holding.is_set() or self.release.exists():
            return
        self.marker.write_text(str(os.getpid()))
        while not self.release.exists():
            trainer.heartbeat.beat(Phase.UPDATE)
            time.sleep(0.2)


class SigintHook(Hook):
    """After the first iteration, each rank appends to ``path`` whether it ignores SIGINT or has taken it over."""

    def __init__(self, path: str) -> None:
        self.path = Path(path)

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        if trainer.iteration == 1:
            with self.path.open("a") as file:
                file.write("ignored\n" if signal.getsignal(signal.SIGINT) == signal.SIG_IGN else "taken\n")
