"""Fencing: the holder's check, run before every write and every delete of a run's storage (``guarded``), that
this process's identity (``ftrain/identity.py``) may still write there.

Before each write, one small read, two on several nodes:
- ``LEASE.json`` (``lease.py``): a generation newer than this process's holds the storage (another run's, this run id's
  started again, or a newer plan of this run on several nodes): nothing of an older generation is written or deleted
  once a newer one exists, even before it writes.
- ``FENCE.json``, on several nodes only (where the identity has an attempt): the newest (generation, attempt) that
  wrote. A node cut off from the others still runs its old attempt; it is refused below the record, which the first
  write of each attempt raises by a compare-and-swap (``cas.py``).

On a file system the check and a commit (a manifest, a marker, a delete) run under the lease's own lock
(``cas.locked``), so no new holder takes the lease in between. On an object store the time between the check and the
write (one request) is left: a process paused exactly there writes once when it goes on; a commit so made is
superseded by the newer generation's history (``lineage.py``). Every manifest records the ``run_id``, ``generation``
and ``attempt`` that committed it.
"""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator

from ftrain.ckpt import cas
from ftrain.ckpt.lease import FENCE, LEASE, LeaseLost, lost_message, read_fence, read_record
from ftrain.ckpt.storage import Storage
from ftrain.identity import Identity


class Fenced(Exception):
    """A newer generation or attempt of the run holds the storage or has committed: this node was cut off from the
    others and must not commit (one-line message)."""


class Fence:
    """The guard of ``identity``'s commits to ``storage``."""

    def __init__(self, storage: Storage, identity: Identity) -> None:
        self.storage = storage.guarded(None)
        self.identity = identity

    @property
    def fields(self) -> dict:
        """What a manifest records of who committed it."""
        ours = self.identity
        attempt = {"attempt": ours.attempt} if ours.attempt is not None else {}
        return {"run_id": ours.run_id, "generation": ours.generation, **attempt}

    @contextlib.contextmanager
    def holding(self, commit: bool = True) -> Iterator[None]:
        """``check``, then the caller's write; a ``commit`` (a manifest, a marker, a delete: one small request) on a
        file system under the lease's lock, released after it. A file's data is checked, then written without the
        lock: it commits nothing by itself, and a slow write must not hold the lease's renewals up."""
        with cas.locked(self.storage, LEASE) if commit else contextlib.nullcontext():
            self.check()
            yield

    @classmethod
    def from_env(cls, storage: Storage) -> Fence | None:
        """The fence of this process's identity; None where it has none (no lease was taken for it)."""
        identity = Identity.from_env()
        return cls(storage, identity) if identity is not None else None

    def check(self) -> dict:
        """Before a write: LeaseLost if another run, or this run alone, started again holds the storage; Fenced if a
        newer plan of this run on several nodes does, or a newer attempt has written; else make sure FENCE.json
        names this attempt. The fields a manifest of this holder records (``fields``)."""
        ours = self.identity
        current = read_record(self.storage)
        if current is not None and (current[0].generation > ours.generation or current[0].run_id != ours.run_id):
            message = lost_message(self.storage, current[0], ours.run_id, ours.generation)
            raise (
                Fenced(message) if current[0].run_id == ours.run_id and ours.attempt is not None else LeaseLost(message)
            )
        fields = self.fields
        if ours.attempt is None:
            return fields
        while True:
            current = cas.read(self.storage, FENCE)
            record = read_fence(current)
            newest = (record.get("generation", 0), record.get("attempt", -1))
            if newest > (ours.generation, ours.attempt):
                raise Fenced(
                    f"attempt {ours.attempt} of generation {ours.generation} is fenced off: attempt {newest[1]} of "
                    f"generation {newest[0]} has committed (this node was cut off from the others), so it commits "
                    "nothing more"
                )
            if newest == (ours.generation, ours.attempt):
                return fields
            raised = json.dumps({"run_id": ours.run_id, "generation": ours.generation, "attempt": ours.attempt})
            try:
                cas.write(self.storage, FENCE, raised.encode(), current[1] if current is not None else None)
                return fields
            except cas.Conflict:
                continue


def guarded(storage: Storage) -> Storage:
    """``storage`` with every write and delete checked against this process's identity (``Fence.holding``): as it is
    where the process has none (no lease was taken for it), or where it is guarded already."""
    if storage.guard is not None:
        return storage
    fence = Fence.from_env(storage)
    return storage.guarded(fence.holding) if fence is not None else storage
