"""Fencing: a commit from an older generation of a run than the newest one that has committed is refused, and so is
a commit of a run that lost the storage's lease to another run (``LeaseToken``, see ``lease.py``).

On several nodes ``ftrain supervise`` numbers its attempts across the nodes (a node that fails or leaves moves every
node to the next one) and hands the run and that number to the workers as ``FTRAIN_GENERATION``. A node cut off from
the others (partitioned, or paused and resumed) still runs its old attempt: a save it had in flight must not commit
after the others went on without it. ``<storage>/FENCE.json`` holds the newest generation that committed: rank 0
reads it before it writes a manifest (one small read per commit), refuses to commit below it, and raises it, by a
compare-and-swap (``cas.py``), at its generation's first commit; every manifest records its ``generation``. What is
left is the time between that read and the manifest's write (one request): a node stopped exactly there commits once
when it goes on (a state of the run from before the others went on, which their newer steps then pass).
"""

from __future__ import annotations

import json
import os

from ftrain.ckpt import cas
from ftrain.ckpt.lease import GENERATION_ENV as LEASE_GENERATION_ENV
from ftrain.ckpt.lease import RUN_ID_ENV, LeaseLost, lost_message, read_record
from ftrain.ckpt.storage import Storage

GENERATION_ENV = "FTRAIN_GENERATION"
"""``RUN:N``: the run (its supervisors' token: a run started again is another one) and its attempt number."""
FENCE = "FENCE.json"


class Fenced(Exception):
    """A newer generation of the run has committed: this one must not (one-line message)."""


class Fence:
    """Rank 0's guard of the commits of generation ``generation`` of run ``run`` to ``storage``."""

    def __init__(self, storage: Storage, run: str, generation: int) -> None:
        self.storage = storage
        self.run = run
        self.generation = generation

    @classmethod
    def from_env(cls, storage: Storage) -> Fence | None:
        """The fence of this process's generation; None where the launcher numbers none (one node: nothing to
        fence)."""
        run, _, generation = os.environ.get(GENERATION_ENV, "").rpartition(":")
        return cls(storage, run, int(generation)) if run and generation.isdigit() else None

    def check(self) -> None:
        """Before a commit: Fenced if a newer generation of this run has committed; else make sure FENCE.json names
        this one (another run's record is replaced: the lease lets one run at a time write the storage)."""
        while True:
            current = cas.read(self.storage, FENCE)
            record = _parse(current[0]) if current is not None else {}
            newest = record.get("generation", -1) if record.get("run") == self.run else -1
            if newest > self.generation:
                raise Fenced(
                    f"generation {self.generation} of the run is fenced off: generation {newest} has committed since "
                    "(this node was cut off from the others), so it commits nothing more"
                )
            if newest == self.generation:
                return
            ours = json.dumps({"run": self.run, "generation": self.generation}).encode()
            try:
                cas.write(self.storage, FENCE, ours, current[1] if current is not None else None)
                return
            except cas.Conflict:
                continue


class LeaseToken:
    """Rank 0's check, right before it writes a manifest, that the lease of ``storage`` is still run ``run_id``'s
    at ``generation`` (see the module doc)."""

    def __init__(self, storage: Storage, run_id: str, generation: int) -> None:
        self.storage = storage
        self.run_id = run_id
        self.generation = generation

    @classmethod
    def from_env(cls, storage: Storage) -> LeaseToken | None:
        """The token of the lease this process's run holds; None where no lease was taken (``ftrain train`` run
        without torchrun's rank 0 or a supervisor holding one)."""
        run_id, generation = os.environ.get(RUN_ID_ENV), os.environ.get(LEASE_GENERATION_ENV, "")
        return cls(storage, run_id, int(generation)) if run_id and generation.isdigit() else None

    def check(self) -> None:
        """LeaseLost if another run has taken the lease since this run's generation."""
        current = read_record(self.storage)
        if current is not None and current[0].run_id != self.run_id and current[0].generation > self.generation:
            raise LeaseLost(lost_message(self.storage, current[0], self.generation))


def _parse(data: bytes) -> dict:
    """A fence record; an unreadable one (a hand edit, a truncated file) counts as none, and is written over."""
    try:
        record = json.loads(data)
    except ValueError:
        return {}
    return record if isinstance(record, dict) and isinstance(record.get("generation"), int) else {}
