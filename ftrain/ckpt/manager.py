"""A rank's checkpoints: resume at the start, and saves at iteration boundaries, coordinated across ranks.

Resuming is ``resume.py``; one save is ``save.py``. This module decides when a save waits and acts on what the
ranks agreed: a committed step (hooks hear of it), a failed one (training goes on; too many in a row, or a failed
final save, stop it), an unloadable one (stop). With ``checkpoint.async_save`` (the default) a save is a snapshot
handed to the rank's writer thread, and up to ``MAX_IN_FLIGHT`` may be in flight; without it, the rank writes and
agrees inline, a plain ``torch.save`` per file.
"""

from __future__ import annotations

import collections
import importlib.metadata
import math
import time
from collections.abc import Callable

from ftrain.ckpt import resume
from ftrain.ckpt.format import COMMON, STATE_FORMAT, shard_name
from ftrain.ckpt.resume import Checkpointable, CheckpointError
from ftrain.ckpt.save import BackgroundWriter, Outcome, StepWriter, snapshot
from ftrain.ckpt.storage import Storage
from ftrain.config import Config
from ftrain.dist import group
from ftrain.errors import UserError

MAX_FAILED_SAVES = 3
"""Saves that may fail in a row (after the storage layer's own retries) before training stops with an error."""
MAX_IN_FLIGHT = 2
"""Saves handed to the writer thread and not yet settled: with two, it may fall one save behind without blocking
the loop."""
WAIT_BEAT = 0.5
"""Seconds between two calls of ``while_waiting`` while a rank waits for a save (its heartbeat: not a hang)."""


class Checkpointer:
    def __init__(
        self, config: Config, info: group.RankInfo, log: Callable[[str], None], robot: dict | None = None
    ) -> None:
        """``robot``: the identity of the robot trained (``ftrain.policy.robot.identity``), for the manifests and the
        resume check."""
        self.config = config
        self.robot = robot
        self.info = info
        self.log = log
        self.storage = Storage.open(config.storage.url, config.storage.options, retries=config.checkpoint.retries)
        if info.distributed and self.storage.url.startswith("memory://"):
            raise UserError(
                f"storage {self.storage.url} lives inside one process, but this run has {info.world_size} ranks: "
                "use a local path, file:// or s3://"
            )
        background = config.checkpoint.async_save
        collectives = group.new_group(config.dist_timeout, info) if background else None
        self._writer = StepWriter(self.storage, config.checkpoint, info, collectives, log)
        self._background = BackgroundWriter(self._writer) if background else None
        self.committed_step: int | None = None
        self.on_commit: Callable[[int, dict], None] = lambda step, manifest: None
        self.while_waiting: Callable[[], None] = lambda: None
        self._pending: collections.deque[tuple[int, bool, dict]] = collections.deque()
        """(step, must commit, snapshot) of the saves handed to the writer thread whose outcome has not been acted on
        yet."""
        self._spare: list[dict] = []
        """Snapshots whose saves are over: the next snapshots copy into their memory."""
        self._failures = 0
        self._checked_loadable = False
        self.last_blocking_s = 0.0
        self._static_meta = {  # computed once: package metadata lookups cost ~10 ms
            "state_format": STATE_FORMAT,
            "world_size": info.world_size,
            "envs_per_rank": config.env.num_envs,
            "env_id": config.env.id,
            "config_hash": config.training_hash(robot),
            **({"robot": robot} if robot is not None else {}),
            "config": config.public_dict(),
            "versions": _versions(),
        }

    def restore(self, trainer: Checkpointable) -> int | None:
        """Load the step to start from into ``trainer`` (see ``resume.py``); the step, or None for a fresh start."""
        resumed = resume.restore(trainer, self.config, self.info, self.storage, self.log, self.robot)
        if resumed.own:
            self.committed_step = resumed.step
        self._static_meta["world_sizes"] = resumed.world_sizes
        return resumed.step

    def save(self, trainer: Checkpointable, wait: bool = False, must_commit: bool = False) -> None:
        """Save the state of ``trainer`` as step ``trainer.iteration``.

        In the background: snapshot now, the writer thread does the rest. Waited for: with ``wait``, the first save
        of a run (it checks that what is saved loads back), and after a failed save until one commits.
        ``must_commit``: the save that ends a run (the last iteration, or a stop): if it fails, CheckpointError
        when it is waited for, instead of training on.
        """
        started = time.perf_counter()
        step = trainer.iteration
        if step == self.committed_step or step in (pending for pending, *_ in self._pending):
            return
        self._settle(MAX_IN_FLIGHT - 1)
        files = {shard_name(self.info.rank): trainer.rank_state()}
        meta = None
        if self.info.is_main:
            files[COMMON] = trainer.common_state()
            meta = self._meta(trainer)
        first = not self._checked_loadable
        self._checked_loadable = True
        if self._background is None:
            self._act_on(self._writer.save(step, files, meta, first), must_commit)
        else:
            copy = snapshot(files, self._spare.pop() if self._spare else None)
            self._background.submit(step, copy, meta, first)
            self._pending.append((step, must_commit, copy))
            if wait or first or self._failures:  # after a failure: one at a time
                self._settle(0)
        self.last_blocking_s = time.perf_counter() - started

    def close(self) -> None:
        """Wait for the saves in flight and act on their outcomes."""
        self._settle(0)

    def shutdown(self) -> None:
        """Let the writer thread end: at once if nothing is in flight, else after its saves (bounded by the
        collectives' timeout, as a dead peer fails them)."""
        if self._background is not None:
            self._background.close(timeout=self.config.dist_timeout + 5)

    def _meta(self, trainer: Checkpointable) -> dict:
        return {
            **self._static_meta,
            "iteration": trainer.iteration,
            "metrics": {  # JSON has no NaN: a metric not measured yet is null
                key: value if math.isfinite(value) else None
                for key, value in trainer.metrics.items()
                if not key.endswith("_time")
            },
        }

    def _settle(self, keep: int) -> None:
        """Act on the agreed outcomes of the oldest saves in flight until at most ``keep`` are left (and on any
        that are already there: the newest committed step is known as soon as possible)."""
        while self._pending and (len(self._pending) > keep or self._background.ready()):
            _, must_commit, copy = self._pending.popleft()
            while (outcome := self._background.take(WAIT_BEAT)) is None:
                self.while_waiting()
            self._spare.append(copy)  # the writer is done with it
            self._act_on(outcome, must_commit)

    def _act_on(self, outcome: Outcome, must_commit: bool) -> None:
        if outcome.kind == "unloadable":
            raise CheckpointError(outcome.detail)
        if outcome.kind == "committed":
            self._failures = 0
            self.committed_step = outcome.step
            self.on_commit(outcome.step, outcome.detail)
            return
        self._failures += 1
        step, detail = outcome.step, outcome.detail
        self.log(f"checkpoint step {step} failed ({self._failures}/{MAX_FAILED_SAVES}), earlier ones intact: {detail}")
        if must_commit:
            raise CheckpointError(
                f"the final checkpoint, step {step}, could not be saved to {self.storage.url}: {detail}"
            )
        if self._failures >= MAX_FAILED_SAVES:
            raise CheckpointError(
                f"{MAX_FAILED_SAVES} checkpoints in a row failed to save to {self.storage.url}; last error: {detail}"
            )


def _versions() -> dict:
    versions = {}
    for package in ("ftrain", "torch", "rsl-rl-lib", "gymnasium", "mujoco"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = None
    return versions
