"""The spool: a node-local copy of a run's newest checkpoints, so that a crash loses seconds of work, not what was
trained while a remote storage was down.

A run on a remote storage (``s3://``...) on one node saves every step to ``<log_dir>/spool`` first (the same layout
and manifests as any storage, on local disk), then to the storage. A restart resumes from the spool's newest step
instead of the storage's when it is newer and continues the storage's history (:meth:`Spool.newest`), so a process
killed during an outage, or just after it before the newest state reached the storage, goes on from where it was.
The storage stays the truth: the spool keeps only its newest ``KEEP`` steps, the run's last step must commit to the
storage, and a machine that is lost takes its spool with it (hence node-local only: on several nodes each spool
would hold only its own node's shards, so there is none). No directory is both a spool and a storage
(``check_place``, before a run starts). Imports no torch at the top: the supervisor runs that check.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from ftrain.ckpt.format import (
    CHECKPOINTS,
    CORRUPT,
    MANIFEST,
    VERIFIED,
    FileEntry,
    StepInfo,
    commit,
    step_dir,
    write_file,
)
from ftrain.ckpt.lease import LEASE
from ftrain.ckpt.retention import delete_step
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage, StorageError
from ftrain.config import Config, local_path
from ftrain.errors import UserError
from ftrain.identity import Identity
from ftrain.log_dir_lock import STORAGE_FILE
from ftrain.redact import display_url

if TYPE_CHECKING:  # torch: not imported by the checks a supervisor runs (check_place)
    from ftrain.comm import group

SPOOL = "spool"
"""The spool's directory in the run's log directory."""
KEEP = 3
"""Spooled steps kept: the newest, and two before it (one of them is usually the storage's newest commit, which
tells that the spool continues the storage's history)."""
FIELD = "spool"
"""The manifest field of a spooled step: ``{"storage": URL, "base": step, "holder": [run id, generation]}``."""


class Spool:
    """The spool of one run on this node: a local storage, written by every rank, committed by rank 0."""

    def __init__(self, storage: Storage, remote_url: str) -> None:
        self.storage = storage
        self.remote_url = remote_url
        identity = Identity.from_env()
        self.holder = [identity.run_id, identity.generation] if identity is not None else None
        """The holder of the storage's lease that this process writes for (``identity.py``): its run and
        generation, which no other holder shares."""

    @classmethod
    def open(cls, config: Config, remote: Storage, info: group.RankInfo) -> Spool | None:
        """The spool of ``config``'s run, or None: switched off, a local storage (it is its own spool), or ranks on
        several nodes (then emptied)."""
        single_node = int(os.environ.get("LOCAL_WORLD_SIZE", info.world_size)) == info.world_size
        if not config.checkpoint.spool or remote.is_local:
            return None
        spool = cls(Storage.open(str(Path(config.log_dir) / SPOOL)), remote.url)
        if single_node:
            return spool
        if info.local_rank == 0:  # what a one-node phase of an elastic run spooled is older than the others' commits
            with contextlib.suppress(StorageError, OSError):  # best effort: nodes on one host may share a log_dir
                spool.clear()
        return None

    @classmethod
    def switched_off(cls, config: Config, remote: Storage) -> Spool | None:
        """The spool an earlier run on ``remote`` left in this log directory, where ``checkpoint.spool=false`` would
        pass over it, or None."""
        path = Path(config.log_dir) / SPOOL
        if config.checkpoint.spool or remote.is_local or not (path / CHECKPOINTS).is_dir():
            return None
        return cls(Storage.open(str(path)), remote.url)

    def refuse_to_pass_over(self, remote: tuple[int, dict] | None) -> None:
        """UserError where this spool, switched off, holds a step that a start with it on would go on from (the
        storage's newest being ``remote``): the start would train on from an older step, and the spooled one, the
        only copy of what was trained since, would no longer continue the storage's history. A spool that does not
        read is passed over: it is optional."""
        try:
            newer = self.newest(remote, True, lambda line: None)
        except (StorageError, OSError, KeyError, TypeError, ValueError):
            return
        if newer is not None:
            older = f"from its step {remote[0]}" if remote is not None else "afresh"
            spool = self.storage.where("")
            raise UserError(
                f"checkpoint.spool=false passes over step {newer[0]} in the spool {spool}, newer than what "
                f"{display_url(self.remote_url)} holds: run with checkpoint.spool=true to go on from it, or delete "
                f"{spool} to go on {older}"
            )

    def write(self, step: int, name: str, data: bytes) -> FileEntry:
        """One file of ``step``; what an earlier attempt at the same step left is replaced (the spool is this
        node's alone)."""
        self.storage.delete(f"{step_dir(step)}/{name}")
        return write_file(self.storage, step, name, data)

    def commit(self, step: int, files: dict[str, FileEntry], meta: dict, base: int | None) -> None:
        """Rank 0: commit ``step`` to the spool, ``base`` being the storage's newest committed step as far as this
        rank knows; then only the newest ``KEEP`` steps stay."""
        self.storage.delete(f"{step_dir(step)}/{MANIFEST}")
        record = {"storage": self.remote_url, "base": base, "holder": self.holder}
        commit(self.storage, step, files, meta | {FIELD: record})
        for info in scan(self.storage)[KEEP:]:
            delete_step(self.storage, info.step)

    def clear(self) -> list[int]:
        """Forget every spooled step (a spool that failed, or a run that starts over); the steps of this storage's
        history it held, which the caller says were deleted."""
        held = [info.step for info in self.held()]
        for info in scan(self.storage):
            delete_step(self.storage, info.step)
        return held

    def held(self) -> list[StepInfo]:
        """The spooled steps of this storage's history that verify, newest first."""
        return [info for info in scan(self.storage) if self._of_this_storage(info)]

    def _of_this_storage(self, info: StepInfo) -> bool:
        return info.status == VERIFIED and _storage_of(info) == self.remote_url

    def newest(self, remote: tuple[int, dict] | None, reachable: bool, log: Callable[[str], None]) -> tuple | None:
        """``(step, manifest)`` of the spooled step to resume from instead of the storage's newest step ``remote``
        (None: the storage has none), or None.

        Reachable storage: the spool's newest step must be newer than the storage's, and continue its history: the
        storage's newest step is the one it was spooled on (``base``), or the spool holds that step too, with the
        same state. A storage that holds no step at all, where the spooled step continued one of its steps: emptied
        since (its bucket made anew, a server that kept it in memory restarted), the spool holding the only copy of
        what was trained, which a fresh start would delete; this run's own spool goes on, another run's is refused
        (UserError), kept, with the two ways on. Unreachable storage: the spooled step must have been written for
        this holder of the storage's lease (the same run and generation), which has held it since, so nothing else
        can have committed to it.
        """
        infos = scan(self.storage)
        ours = [info for info in infos if self._of_this_storage(info)]
        newer_than = max(ours[0].step if ours else -1, remote[0] if remote is not None else -1)
        damaged = [
            info
            for info in infos
            if info.status == CORRUPT and info.step > newer_than and _storage_of(info) in (self.remote_url, None)
        ]  # None: its manifest does not read
        if damaged:
            problems = "; ".join(map(str, damaged[0].problems))
            log(f"not resuming from spooled step {damaged[0].step} ({self.storage.url}): it is corrupt ({problems})")
        if not ours:
            return None
        newest = ours[0]
        record = newest.manifest[FIELD]
        if not reachable:
            trusted = self.holder is not None and record.get("holder") == self.holder
            why = "" if trusted else "it was written for another holder of the storage"
        elif remote is None and record["base"] is not None:
            if self.holder is None or (record.get("holder") or [None])[0] != self.holder[0]:
                raise UserError(self._emptied(newest.step, record["base"]))
            trusted, why = True, ""
        elif remote is not None and remote[0] >= newest.step:
            return None
        else:
            remote_step = remote[0] if remote is not None else None
            same = {info.step: info.manifest.get("state_sha256") for info in ours}
            trusted = record["base"] == remote_step or (
                remote is not None and same.get(remote_step) == remote[1].get("state_sha256")
            )
            why = "" if trusted else f"the storage's newest step {remote_step} is not in its history"
        if not trusted:
            log(f"not resuming from spooled step {newest.step} ({self.storage.url}): {why}")
            return None
        return newest.step, newest.manifest

    def _emptied(self, step: int, base: int) -> str:
        spooled = self.storage.where(step_dir(step))
        return (
            f"{self.remote_url} holds no step, but the spool holds step {step} of its history, spooled on its step "
            f"{base} by an earlier run ({spooled}): to go on from it, copy that directory to "
            f"{self.remote_url}/{step_dir(step)} and run again; resume=never starts afresh and empties the spool"
        )


def check_place(config: Config) -> None:
    """UserError where a spool and a storage would be one directory: this run's spool, ``<log_dir>/spool``, holds
    another run's storage (its lease), or this run's local storage is another run's spool (the directory above it is
    the log directory of a run on a remote storage). Each run would delete the other's steps: the spool its storage's,
    the storage's clean-up the spool's. And where ``resume=`` names a step in this run's spool, which a start that
    does not resume from the spool empties before the step is read (on several nodes, before anything)."""
    url = config.storage.url
    if (path := local_path(url)) and os.path.basename(path := os.path.realpath(path)) == SPOOL:
        holder = Path(path).parent / STORAGE_FILE
        with contextlib.suppress(OSError):
            if "://" in (other := holder.read_text().strip()):  # a local storage's run keeps no spool
                raise UserError(
                    f"storage {url} is the spool of the run on {other}, whose log directory is {holder.parent}: "
                    "that run empties it: pass a directory of its own"
                )
    spool = Path(config.log_dir) / SPOOL
    if path or not config.checkpoint.spool:
        return
    if (spool / LEASE).exists():
        raise UserError(
            f"log directory {config.log_dir} would keep this run's spool in {spool}, which is the storage of another "
            f"run (it holds {LEASE}): give the run on {display_url(url)} a log directory of its own with log_dir=DIR"
        )
    if config.resume not in ("auto", "never") and _inside(config.resume, spool):
        raise UserError(
            f"resume={display_url(config.resume)} is in this run's spool, which a start that does not resume from it "
            f"empties before the step is read: copy the step's directory out of {spool} (into "
            f"{display_url(url).rstrip('/')}/{CHECKPOINTS}/ to go on from it with resume=auto, or elsewhere for "
            "resume=) and run again"
        )


def _inside(url: str, root: Path) -> bool:
    """Whether ``url`` (a local path or ``file://`` URL) lies in ``root``, by any name (links, ``..``)."""
    path, real_root = local_path(url), os.path.realpath(root)
    return bool(path) and os.path.commonpath([os.path.realpath(path), real_root]) == real_root


def _storage_of(info: StepInfo) -> str | None:
    """The storage a spooled step was written for (None where its manifest does not read)."""
    return (info.manifest or {}).get(FIELD, {}).get("storage")
