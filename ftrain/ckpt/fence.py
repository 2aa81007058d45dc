"""Fencing: rank 0's check, right before it writes a manifest, that its identity (``ftrain/identity.py``) may still
commit to the storage.

Two reads, one small request each:
- ``LEASE.json`` (``lease.py``): a generation newer than this process's holds the storage. Another run's, or this run
  id's started again (a requeued job, the same command again while a process of the old one still ran), or a newer
  plan of this run on several nodes (node 0's supervisor started again, a run started anew on etcd), whose maker took
  the next generation. So nothing of an older generation commits once a newer one exists, even before it commits.
- ``FENCE.json``, on several nodes only (where the identity has an attempt): the newest (generation, attempt) that
  committed. A node cut off from the others (partitioned, or paused and resumed) still runs its old attempt: a save
  it had in flight must not commit after the others went on without it. Rank 0 refuses to commit below the record,
  and raises it, by a compare-and-swap (``cas.py``), at its attempt's first commit. One node runs one attempt at a
  time (its supervisor confirms the old one dead before the next starts), so it has nothing to fence.

Every manifest records the ``run_id``, ``generation`` and ``attempt`` that committed it. What is left is the time
between the reads and the manifest's write (one request): a process stopped exactly there commits once when it goes
on (a state of the run from before the others went on, which their newer steps then pass).
"""

from __future__ import annotations

import json

from ftrain.ckpt import cas
from ftrain.ckpt.lease import FENCE, LeaseLost, lost_message, read_fence, read_record
from ftrain.ckpt.storage import Storage
from ftrain.identity import Identity


class Fenced(Exception):
    """A newer generation or attempt of the run holds the storage or has committed: this node was cut off from the
    others and must not commit (one-line message)."""


class Fence:
    """The guard of ``identity``'s commits to ``storage``."""

    def __init__(self, storage: Storage, identity: Identity) -> None:
        self.storage = storage
        self.identity = identity

    @classmethod
    def from_env(cls, storage: Storage) -> Fence | None:
        """The fence of this process's identity; None where it has none (no lease was taken for it)."""
        identity = Identity.from_env()
        return cls(storage, identity) if identity is not None else None

    def check(self) -> dict:
        """Before a commit: LeaseLost if another run, or this run alone, started again holds the storage; Fenced if a
        newer plan of this run on several nodes does, or a newer attempt has committed; else make sure FENCE.json
        names this attempt. The fields the manifest records."""
        ours = self.identity
        current = read_record(self.storage)
        if current is not None and (current[0].generation > ours.generation or current[0].run_id != ours.run_id):
            message = lost_message(self.storage, current[0], ours.run_id, ours.generation)
            raise (
                Fenced(message) if current[0].run_id == ours.run_id and ours.attempt is not None else LeaseLost(message)
            )
        fields = {"run_id": ours.run_id, "generation": ours.generation}
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
                return fields | {"attempt": ours.attempt}
            raised = json.dumps({"run_id": ours.run_id, "generation": ours.generation, "attempt": ours.attempt})
            try:
                cas.write(self.storage, FENCE, raised.encode(), current[1] if current is not None else None)
                return fields | {"attempt": ours.attempt}
            except cas.Conflict:
                continue
