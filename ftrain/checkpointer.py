"""Coordinated checkpoints across ranks: which step to resume, sharded asynchronous saves, commit, retention.

The format and the single-process rules (digests, manifest, verification, retention plans) live in
``checkpoint.py``; this module adds the distributed protocol on top:

- Resume: rank 0 picks the step (newest that verifies, quarantining bad ones) and broadcasts its decision; every
  rank then reads ``common.pt`` and its own shard, checking both against the manifest.
- Save: at the iteration boundary each rank encodes its state to bytes (the snapshot; training may go on), then a
  background thread writes the shard, the ranks gather their digests over a separate gloo group (async
  collectives on the default group deadlocked in a probe), rank 0 commits the manifest and applies retention,
  and broadcasts the outcome so every rank agrees whether the step counts.
"""

from __future__ import annotations

import datetime
import importlib.metadata
import math
import queue
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
import torch.distributed as dist

from ftrain import checkpoint, distributed
from ftrain.algorithm import state_digest
from ftrain.checkpoint import encode
from ftrain.config import Config
from ftrain.errors import UserError
from ftrain.storage import Storage

if TYPE_CHECKING:
    from ftrain.trainer import Trainer

COMMON = "common.pt"
MAX_FAILED_SAVES = 3
"""Saves that may fail in a row (after the storage layer's own retries) before training stops with an error."""


def shard_name(rank: int) -> str:
    return f"rank-{rank:05d}.pt"


class CheckpointError(RuntimeError):
    """Saving or loading a checkpoint failed in a way training must not run on from (one-line message)."""


class Checkpointer:
    def __init__(self, config: Config, info: distributed.RankInfo, log: Callable[[str], None]) -> None:
        self.config = config
        self.info = info
        self.log = log
        self.storage = Storage.open(config.storage.url, config.storage.options, retries=config.checkpoint.retries)
        if info.distributed and self.storage.url.startswith("memory://"):
            raise UserError(
                f"storage {self.storage.url} lives inside one process, but this run has {info.world_size} ranks: "
                "use a local path, file:// or s3://"
            )
        timeout = datetime.timedelta(seconds=config.dist_timeout)
        self.save_group = dist.new_group(backend="gloo", timeout=timeout) if info.distributed else None
        self.committed_step: int | None = None
        self.on_commit: Callable[[int, dict], None] = lambda step, manifest: None
        # one long-lived writer thread: starting a thread per save would block the loop until the new thread, which
        # starts by encoding (holding the GIL), lets go of it
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._done = threading.Event()
        self._in_flight = False
        self._writer_thread = threading.Thread(target=self._writer, name="ftrain-checkpoint-writer", daemon=True)
        self._writer_thread.start()
        self._outcome: tuple | None = None
        self._must_commit = False
        self._failures = 0
        self._occupied: set[int] = set()
        """Corrupt or quarantined steps past the resume point: replaced only when this run saves them again."""
        self._checked_loadable = False
        self._unloadable: str | None = None
        self.last_blocking_s = 0.0
        self._static_meta = {  # computed once: package metadata lookups cost ~10 ms
            "world_size": info.world_size,
            "envs_per_rank": config.env.num_envs,
            "env_id": config.env.id,
            "config_hash": config.training_hash(),
            "config": config.public_dict(),
            "versions": _versions(),
        }

    # --- resume ------------------------------------------------------------------------------------------------

    def restore(self, trainer: Trainer) -> int | None:
        """Load the step rank 0 chose into ``trainer``; the step, or None for a fresh start.

        Every rank reads and checks its own files; the ranks then agree whether all of them loaded, so a file that
        fails on one rank stops all of them with the same message (and quarantines the step for the next try).
        """
        decision = self._decide_resume() if self.info.is_main else None
        decision = distributed.broadcast_object(decision, self.info)
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
            common = checkpoint.read_verified(storage, step, COMMON, manifest)
            shard = checkpoint.read_verified(storage, step, shard_name(self.info.rank), manifest)
            trainer.load_state(common, shard)
            failure = None
        except (checkpoint.CorruptCheckpoint, KeyError, ValueError, RuntimeError) as exc:
            failure = f"rank {self.info.rank}: {exc}"
        failures = [f for f in distributed.all_gather_object(failure, self.info) if f]
        if failures:
            where = storage.where(checkpoint.step_dir(step))
            if url is None and self.info.is_main:
                checkpoint.quarantine(self.storage, step, "; ".join(failures))
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
                if any(info.status == checkpoint.VERIFIED for info in checkpoint.scan(self.storage)):
                    raise UserError(
                        f"resume=never but {self.storage.url} already holds checkpoints: "
                        "use resume=auto to continue, or a new --storage"
                    )
                return ("fresh", "resume=never: starting fresh", checkpoint.clear_newer(self.storage, 0, self.log))
            if resume == "auto":
                found = checkpoint.select_resume(self.storage, log=self.log)
                if found is None:
                    occupied = checkpoint.clear_newer(self.storage, 0, log=self.log)
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
                _, step, manifest = checkpoint.resolve_checkpoint_url(resume, self.config.storage.options, self.log)
                url = checkpoint.parse_checkpoint_url(resume)[0]
            self._check_compatible(step, manifest)
            return ("resume", url, step, manifest, checkpoint.clear_newer(self.storage, step, log=self.log))
        except UserError as error:
            return ("error", str(error))

    def _check_compatible(self, step: int, manifest: dict) -> None:
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

    def save(self, trainer: Trainer, wait: bool = False, must_commit: bool = False) -> None:
        """Snapshot now (a copy of every tensor, well under a millisecond); encode, digest and write in the
        background unless ``wait`` or ``checkpoint.async_save=false``. The first save of a run is waited for: it
        checks that what is saved loads back.

        ``must_commit``: the save that ends a run (the last iteration, or a stop): if it fails, CheckpointError
        when it is waited for, instead of training on.
        """
        started = time.perf_counter()
        self._join()
        step = trainer.iteration
        if step == self.committed_step:
            return
        if step in self._occupied:
            self._replace_occupied(step)
        shard_state = _snapshot(trainer.rank_state())
        common_state = meta = None
        if self.info.is_main:
            common_state = _snapshot(trainer.common_state())
            meta = self._meta(trainer)
        self._must_commit = must_commit
        self._done.clear()
        self._in_flight = True
        self._jobs.put((step, common_state, shard_state, meta))
        if wait or not self.config.checkpoint.async_save or not self._checked_loadable:
            self._join()
        self.last_blocking_s = time.perf_counter() - started

    def close(self) -> None:
        """Wait for the save in flight and act on its outcome."""
        self._join()

    def stop_writer(self) -> None:
        """Let the writer thread end (after any save in flight): the process must not exit under it."""
        self._jobs.put(None)
        self._writer_thread.join()

    def _writer(self) -> None:
        while (job := self._jobs.get()) is not None:
            try:
                self._write(*job)
            finally:
                self._done.set()

    def _replace_occupied(self, step: int) -> None:
        """A corrupt or quarantined directory holds this step: rank 0 deletes it; no rank writes before that."""
        if self.info.is_main:
            checkpoint.replace_bad(self.storage, step, log=self.log)
        if self.save_group is not None:
            dist.barrier(group=self.save_group)
        self._occupied.discard(step)

    def _meta(self, trainer: Trainer) -> dict:
        return {
            **self._static_meta,
            "iteration": trainer.iteration,
            "metrics": {  # JSON has no NaN: a metric not measured yet is null
                key: value if math.isfinite(value) else None
                for key, value in trainer.metrics.items()
                if not key.endswith("_time")
            },
        }

    def _write(self, step: int, common_state: dict | None, shard_state: dict, meta: dict | None) -> None:
        """Runs on every rank (normally in the background thread); the collectives use ``save_group``."""
        entries, error = {}, None
        try:
            encoded = {shard_name(self.info.rank): encode(shard_state)}
            if common_state is not None:
                encoded[COMMON] = encode(common_state)
                meta["state_sha256"] = state_digest(common_state["learned"])
                if "teacher" in common_state:
                    meta["teacher"] = common_state["teacher"]
            if not self._checked_loadable:
                self._check_loadable(encoded)
            for name, data in encoded.items():
                entries[name] = checkpoint.write_file(self.storage, step, name, data)
        except Exception as exc:  # any storage failure: reported, agreed on, never fatal by itself
            error = f"rank {self.info.rank}: {exc}"
        reports = distributed.all_gather_object((entries, error), self.info, self.save_group)
        outcome = None
        if self.info.is_main:
            outcome = self._commit(step, reports, meta)
        self._outcome = distributed.broadcast_object(outcome, self.info, self.save_group)

    def _check_loadable(self, encoded: dict[str, bytes]) -> None:
        """Once per run: what is saved must load back with ``weights_only=True`` (a numpy value in a hook's state or
        in the metrics would be saved and verified, yet never loadable)."""
        for name, data in encoded.items():
            try:
                checkpoint.decode(data, name)
            except checkpoint.CorruptCheckpoint as exc:
                self._unloadable = (
                    f"{exc}: hooks and metrics must keep plain data (tensors, numbers, strings, lists, dicts)"
                )
                raise
        self._checked_loadable = True

    def _commit(self, step: int, reports: list, meta: dict) -> tuple:
        errors = [error for _, error in reports if error]
        if errors:
            return ("failed", step, "; ".join(errors))
        files = {name: entry for entries, _ in reports for name, entry in entries.items()}
        try:
            manifest = checkpoint.commit(self.storage, step, files, meta)
        except Exception as exc:
            return ("failed", step, f"commit: {exc}")
        try:
            self._apply_retention()
        except Exception as exc:
            self.log(f"retention after step {step} failed (checkpoints kept): {exc}")
        return ("committed", step, manifest)

    def _apply_retention(self) -> None:
        policy = self.config.checkpoint
        steps = checkpoint.scan(self.storage)
        doomed = checkpoint.retention_plan(
            steps, policy.keep_last, policy.keep_best, policy.best_metric, policy.keep_every, policy.pinned
        )
        for step in doomed:
            checkpoint.delete_step(self.storage, step)

    def _join(self) -> None:
        """Wait for the save in flight and act on its agreed outcome (on the main thread)."""
        if not self._in_flight:
            return
        self._done.wait()
        self._in_flight = False
        outcome, self._outcome = self._outcome, None
        if outcome is None:
            raise CheckpointError("the checkpoint writer stopped without an outcome (a peer died mid-save?)")
        if self._unloadable:
            raise CheckpointError(self._unloadable)
        kind, step, detail = outcome
        if kind == "committed":
            self._failures = 0
            self.committed_step = step
            self.on_commit(step, detail)
            return
        self._failures += 1
        self.log(f"checkpoint step {step} failed ({self._failures}/{MAX_FAILED_SAVES}), earlier ones intact: {detail}")
        if self._must_commit:
            raise CheckpointError(
                f"the final checkpoint, step {step}, could not be saved to {self.storage.url}: {detail}"
            )
        if self._failures >= MAX_FAILED_SAVES:
            raise CheckpointError(
                f"{MAX_FAILED_SAVES} checkpoints in a row failed to save to {self.storage.url}; last error: {detail}"
            )


def _snapshot(state: object) -> object:
    """A copy of ``state`` that training can no longer change: every tensor cloned, containers rebuilt."""
    if isinstance(state, torch.Tensor):
        return state.detach().clone()
    if isinstance(state, dict):
        return {key: _snapshot(value) for key, value in state.items()}
    if isinstance(state, (list, tuple)):
        return type(state)(_snapshot(value) for value in state)
    return state


def _versions() -> dict:
    versions = {}
    for package in ("ftrain", "torch", "rsl-rl-lib", "gymnasium", "mujoco"):
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = None
    return versions
