"""Coordinated checkpoints across ranks: which step to resume, sharded asynchronous saves, commit, retention.

The format and the single-process rules (digests, manifest, verification, retention plans) live in
``format.py``, ``steps.py`` and ``retention.py``; this module adds the distributed protocol on top:

- Resume: rank 0 picks the step (newest that verifies, quarantining bad ones) and broadcasts its decision; every
  rank then reads ``common.pt`` and its own shard, checking both against the manifest.
- Save: at the iteration boundary each rank packs its state into memory it shares with its save helper (one copy
  of every tensor, which training can no longer change: the snapshot; see ``packing.py``) and hands it over; the
  helper is a process at idle CPU priority (``helper.py``). The helpers encode and write the shards, gather their
  digests through torchrun's key-value store, and rank 0's helper commits the manifest and applies retention;
  every rank reads the agreed outcome back at a later save (or at once, for a synchronous one), so all ranks agree
  whether the step counts.
"""

from __future__ import annotations

import collections
import importlib.metadata
import math
import time
from collections.abc import Callable
from typing import Protocol

from ftrain.ckpt.format import (
    COMMON,
    RESUMABLE_STATE_FORMATS,
    STATE_FORMAT,
    VERIFIED,
    CorruptCheckpoint,
    parse_checkpoint_url,
    read_verified,
    shard_name,
    step_dir,
)
from ftrain.ckpt.helper import SaverClient, SaverGone
from ftrain.ckpt.steps import clear_newer, quarantine, resolve_checkpoint_url, scan, select_resume
from ftrain.ckpt.storage import Storage
from ftrain.config import Config
from ftrain.dist import group
from ftrain.errors import UserError

MAX_FAILED_SAVES = 3
"""Saves that may fail in a row (after the storage layer's own retries) before training stops with an error."""
MAX_IN_FLIGHT = 2
"""Saves handed to the helper and not yet settled: with two, the helper, which only gets CPU time that training
leaves, may fall one save behind without blocking the loop."""


class Checkpointable(Protocol):
    """What a checkpoint saves and restores: the trainer, as this package sees it."""

    iteration: int
    metrics: dict[str, float]

    def common_state(self) -> dict:
        """The state all ranks share, saved once by rank 0 (``common.pt``)."""

    def rank_state(self) -> dict:
        """This rank's own state (its shard)."""

    def load_state(self, common: dict, rank: dict) -> None:
        """Restore what ``common_state`` and ``rank_state`` returned."""


class CheckpointError(RuntimeError):
    """Saving or loading a checkpoint failed in a way training must not run on from (one-line message)."""


class Checkpointer:
    def __init__(self, config: Config, info: group.RankInfo, log: Callable[[str], None]) -> None:
        self.config = config
        self.info = info
        self.log = log
        self.storage = Storage.open(config.storage.url, config.storage.options, retries=config.checkpoint.retries)
        if info.distributed and self.storage.url.startswith("memory://"):
            raise UserError(
                f"storage {self.storage.url} lives inside one process, but this run has {info.world_size} ranks: "
                "use a local path, file:// or s3://"
            )
        self._saver = SaverClient(config, info)
        """Encoding, writing, agreeing and committing: a helper process at idle priority (see helper.py)."""
        self.committed_step: int | None = None
        self.on_commit: Callable[[int, dict], None] = lambda step, manifest: None
        self._pending: collections.deque[tuple[int, bool]] = collections.deque()
        """(step, must commit) of the saves handed to the helper whose outcome has not been acted on yet."""
        self._failures = 0
        self._occupied: set[int] = set()
        """Corrupt or quarantined steps past the resume point: replaced only when this run saves them again."""
        self._checked_loadable = False
        self.last_blocking_s = 0.0
        self._static_meta = {  # computed once: package metadata lookups cost ~10 ms
            "state_format": STATE_FORMAT,
            "world_size": info.world_size,
            "envs_per_rank": config.env.num_envs,
            "env_id": config.env.id,
            "config_hash": config.training_hash(),
            "config": config.public_dict(),
            "versions": _versions(),
        }

    # --- resume ------------------------------------------------------------------------------------------------

    def restore(self, trainer: Checkpointable) -> int | None:
        """Load the step rank 0 chose into ``trainer``; the step, or None for a fresh start.

        Every rank reads and checks its own files; the ranks then agree whether all of them loaded, so a file that
        fails on one rank stops all of them with the same message (and quarantines the step for the next try).
        """
        decision = self._decide_resume() if self.info.is_main else None
        decision = group.broadcast_object(decision, self.info)
        kind = decision[0]
        if kind == "error":
            raise UserError(decision[1])
        self._occupied = set(decision[-1])
        if kind == "fresh":
            self.log(decision[1])
            return None
        _, url, step, manifest, _ = decision
        storage = self.storage if url is None else Storage.open(url, self.config.storage.options)
        try:
            common = read_verified(storage, step, COMMON, manifest)
            shard = read_verified(storage, step, shard_name(self.info.rank), manifest)
            trainer.load_state(common, shard)
            failure = None
        except (CorruptCheckpoint, KeyError, ValueError, RuntimeError) as exc:
            failure = f"rank {self.info.rank}: {exc}"
        failures = [f for f in group.all_gather_object(failure, self.info) if f]
        if failures:
            where = storage.where(step_dir(step))
            if url is None and self.info.is_main:
                quarantine(self.storage, step, "; ".join(failures))
            raise CheckpointError(
                f"checkpoint {where} could not be loaded ({'; '.join(failures)}): quarantined, "
                "the next start falls back to an older step"
            )
        if url is None:
            self.committed_step = step
        self.log(f"resumed from step {step} ({'this storage' if url is None else url}), iteration {trainer.iteration}")
        return step

    def _decide_resume(self) -> tuple:
        """On rank 0: ("fresh", why, occupied) | ("resume", url or None, step, manifest, occupied) | ("error", why).

        ``occupied``: corrupt or quarantined steps newer than the start, kept until this run saves them again.
        """
        try:
            resume = self.config.resume
            if resume == "never":
                if any(info.status == VERIFIED for info in scan(self.storage)):
                    raise UserError(
                        f"resume=never but {self.storage.url} already holds checkpoints: "
                        "use resume=auto to continue, or a new --storage"
                    )
                return ("fresh", "resume=never: starting fresh", clear_newer(self.storage, 0, self.log))
            if resume == "auto":
                found = select_resume(self.storage, log=self.log)
                if found is None:
                    occupied = clear_newer(self.storage, 0, log=self.log)
                    if occupied:
                        raise UserError(
                            f"no checkpoint in {self.storage.url} verifies, and steps {sorted(occupied)} are corrupt: "
                            f"inspect them (ftrain ckpt ls {self.storage.url}), then remove them (ftrain ckpt prune "
                            "--drop-bad) to start over, or use another --storage"
                        )
                    return ("fresh", f"no verified checkpoint in {self.storage.url}: starting fresh", [])
                step, manifest = found
                url = None
            else:
                _, step, manifest = resolve_checkpoint_url(resume, self.config.storage.options, self.log)
                url = parse_checkpoint_url(resume)[0]
            self._check_compatible(step, manifest)
            return ("resume", url, step, manifest, clear_newer(self.storage, step, log=self.log))
        except UserError as error:
            return ("error", str(error))

    def _check_compatible(self, step: int, manifest: dict) -> None:
        written = manifest.get("state_format", 1)
        if written not in RESUMABLE_STATE_FORMATS:
            formats = " and ".join(map(str, RESUMABLE_STATE_FORMATS))
            raise UserError(
                f"checkpoint step {step} holds training state in format {written}, this ftrain resumes formats "
                f"{formats}: resume it with the ftrain version that wrote it ({manifest['versions']}), "
                "or start another --storage (its policy still loads)"
            )
        if manifest["world_size"] != self.info.world_size:
            raise UserError(
                f"checkpoint step {step} was written by {manifest['world_size']} ranks but this run has "
                f"{self.info.world_size}: run with --nproc-per-node={manifest['world_size']} "
                "(environment state is per rank)"
            )
        if manifest["envs_per_rank"] != self.config.env.num_envs:
            raise UserError(
                f"checkpoint step {step} has env.num_envs={manifest['envs_per_rank']} per rank, "
                f"the config has {self.config.env.num_envs}: set env.num_envs={manifest['envs_per_rank']}"
            )
        saved = manifest["config"]
        if saved["env"]["id"] != self.config.env.id or saved["policy"] != self.config.public_dict()["policy"]:
            raise UserError(
                f"checkpoint step {step} holds a {saved['env']['id']} policy {saved['policy']}, the config asks for "
                f"a {self.config.env.id} policy {self.config.public_dict()['policy']}: they cannot be loaded into "
                "each other (not even with allow_config_change=true): use another --storage"
            )
        if manifest["config_hash"] != self.config.training_hash() and not self.config.allow_config_change:
            raise UserError(
                f"checkpoint step {step} was trained with a different config (hash {manifest['config_hash']}, "
                f"now {self.config.training_hash()}): restore the config, or pass allow_config_change=true"
            )

    # --- save --------------------------------------------------------------------------------------------------

    def save(self, trainer: Checkpointable, wait: bool = False, must_commit: bool = False) -> None:
        """Snapshot now (every tensor packed into shared memory, about a millisecond) and hand it to the save helper,
        which encodes, writes and commits it in the background; up to ``MAX_IN_FLIGHT`` saves may be in flight.
        Waited for: with ``wait``, with ``checkpoint.async_save=false``, the first save of a run (it checks that what
        is saved loads back), and after a failed save until one commits.

        ``must_commit``: the save that ends a run (the last iteration, or a stop): if it fails, CheckpointError
        when it is waited for, instead of training on.
        """
        started = time.perf_counter()
        step = trainer.iteration
        if step == self.committed_step or step in (pending for pending, _ in self._pending):
            return
        self._settle(MAX_IN_FLIGHT - 1)
        replace = step in self._occupied
        self._occupied.discard(step)
        states = {shard_name(self.info.rank): trainer.rank_state()}
        meta = None
        if self.info.is_main:
            states[COMMON] = trainer.common_state()
            meta = self._meta(trainer)
        first = not self._checked_loadable
        try:
            self._saver.save(step, states, meta, first, replace)
        except SaverGone as exc:
            raise CheckpointError(str(exc)) from None
        self._checked_loadable = True
        self._pending.append((step, must_commit))
        if wait or not self.config.checkpoint.async_save or first or self._failures:  # after a failure: one at a time
            self._settle(0)
        self.last_blocking_s = time.perf_counter() - started

    def close(self) -> None:
        """Wait for the saves in flight and act on their outcomes."""
        self._settle(0)

    def wait_ready(self) -> None:
        """Wait until the save helper is ready (for measurements of the steady state; saves wait by themselves)."""
        try:
            self._saver.wait_ready()
        except SaverGone as exc:
            raise CheckpointError(str(exc)) from None

    def shutdown(self) -> None:
        """Let the save helper finish and end: the rank must not exit under it."""
        self._saver.close()

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
        try:
            while len(self._pending) > keep or (self._pending and self._saver.has_message()):
                _, must_commit = self._pending.popleft()
                self._act_on(self._saver.receive(), must_commit)
        except SaverGone as exc:
            raise CheckpointError(f"{exc}; a peer may have died mid-save") from None

    def _act_on(self, outcome: tuple, must_commit: bool) -> None:
        kind, step, detail = outcome
        if kind == "unloadable":
            raise CheckpointError(detail)
        if kind == "committed":
            self._failures = 0
            self.committed_step = step
            self.on_commit(step, detail)
            return
        self._failures += 1
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
