"""Fencing: a commit from an older generation of a run than the newest one that has committed is refused, and so is
a commit of a run that lost the storage's lease to another run (``LeaseToken``, see ``lease.py``).

On several nodes ``ftrain supervise`` numbers its attempts across the nodes (a node that fails or leaves moves every
node to the next one) and hands the workers their generation as ``FTRAIN_GENERATION``: the plan's token, the
token's epoch and the attempt. A node cut off from the others (partitioned, or paused and resumed) still runs its old
attempt: a save it had in flight must not commit after the others went on without it. ``<storage>/FENCE.json`` holds
the newest (epoch, attempt) that committed: rank 0 reads it before it writes a manifest (one small read per commit),
refuses to commit below it, and raises it, by a compare-and-swap (``cas.py``), at its generation's first commit;
every manifest records its ``generation`` and ``epoch``. What is left is the time between that read and the
manifest's write (one request): a node stopped exactly there commits once when it goes on (a state of the run from
before the others went on, which their newer steps then pass).

Epochs order the tokens. A plan's token is new whenever node 0's supervisor starts again (c10d), or a run starts
anew on etcd, while nodes of the old token may still run; so the first supervisor to launch an attempt of a token
takes the next epoch in ``FENCE.json`` (``epoch_of``: every node of the token reads the same one there), and raises
the fence to it at once: from then on nothing of an older token commits, whatever its attempt number.
"""

from __future__ import annotations

import json
import os
import time

from ftrain.ckpt import cas
from ftrain.ckpt.lease import GENERATION_ENV as LEASE_GENERATION_ENV
from ftrain.ckpt.lease import RUN_ID_ENV, LeaseLost, lost_message, read_record
from ftrain.ckpt.storage import Storage

GENERATION_ENV = "FTRAIN_GENERATION"
"""``RUN:EPOCH:N``: the run (its supervisors' token: a run started again is another one), the token's epoch
(``epoch_of``) and its attempt number."""
FENCE = "FENCE.json"
EPOCHS_KEPT = 32
"""Tokens whose epochs ``FENCE.json`` remembers, the newest."""
EPOCH_WAIT = 120.0
"""Seconds a node that does not number a token waits for its maker to have numbered it (see ``epoch_of``)."""


class Fenced(Exception):
    """A newer generation of the run has committed: this one must not (one-line message)."""


class Fence:
    """Rank 0's guard of the commits of attempt ``generation`` of run ``run`` (its token), whose epoch is ``epoch``,
    to ``storage``."""

    def __init__(self, storage: Storage, run: str, epoch: int, generation: int) -> None:
        self.storage = storage
        self.run = run
        self.epoch = epoch
        self.generation = generation

    @classmethod
    def from_env(cls, storage: Storage) -> Fence | None:
        """The fence of this process's generation; None where the launcher numbers none (one node: nothing to
        fence)."""
        run, epoch, generation = [*os.environ.get(GENERATION_ENV, "").split(":"), "", ""][:3]
        numbers = epoch.isdigit() and generation.isdigit()
        return cls(storage, run, int(epoch), int(generation)) if run and numbers else None

    def check(self) -> None:
        """Before a commit: Fenced if a newer (epoch, attempt) has committed, or the fence was raised to a newer
        token's epoch; else make sure FENCE.json names this generation."""
        while True:
            current = cas.read(self.storage, FENCE)
            record = _parse(current[0]) if current is not None else {}
            newest, ours = (record.get("epoch", 0), record.get("generation", -1)), (self.epoch, self.generation)
            if newest > ours or (newest == ours and record.get("run") != self.run):
                raise Fenced(
                    f"generation {self.generation} (epoch {self.epoch}) of the run is fenced off: generation "
                    f"{newest[1]} of epoch {newest[0]} is newer (this node was cut off from the others), so it commits "
                    "nothing more"
                )
            if newest == ours:
                return
            ours = json.dumps({**record, "run": self.run, "epoch": self.epoch, "generation": self.generation})
            try:
                cas.write(self.storage, FENCE, ours.encode(), current[1] if current is not None else None)
                return
            except cas.Conflict:
                continue


def epoch_of(storage: Storage, run: str, allocate: bool = True, wait: float = EPOCH_WAIT) -> int:
    """The epoch of token ``run``: the one ``FENCE.json`` records for it; else, if ``allocate`` (the token's maker:
    node 0's supervisor with c10d; any node on etcd, whose plan is read fresh before every launch), the next one,
    which it records, raising the fence to it (see the module doc). Others wait up to ``wait`` seconds for the maker
    to record it, then take 0, below every recorded epoch: a token never given one commits nothing past another's.
    A token only its maker numbers cannot take an epoch after a newer token (its maker, gone, is what made the newer
    one start)."""
    deadline = time.monotonic() + wait
    while True:
        current = cas.read(storage, FENCE)
        record = _parse(current[0]) if current is not None else {}
        epochs = record.get("epochs") if isinstance(record.get("epochs"), dict) else {}
        if isinstance(epochs.get(run), int):
            break
        if not allocate:
            if time.monotonic() > deadline:
                return 0
            time.sleep(0.5)
            continue
        epoch = max([record.get("epoch", 0), *epochs.values()]) + 1
        epochs = dict(list(epochs.items())[-(EPOCHS_KEPT - 1) :]) | {run: epoch}
        raised = {"run": run, "epoch": epoch, "generation": -1, "epochs": epochs}
        try:
            cas.write(storage, FENCE, json.dumps(raised).encode(), current[1] if current is not None else None)
            break
        except cas.Conflict:
            continue
    return epochs[run]


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
        """LeaseLost if a newer generation holds the lease: another run, or this run id again after this one's
        processes were all gone (a requeued job, while a process of the old one still runs)."""
        current = read_record(self.storage)
        if current is not None and current[0].generation > self.generation:
            raise LeaseLost(lost_message(self.storage, current[0], self.run_id, self.generation))


def _parse(data: bytes) -> dict:
    """A fence record; an unreadable one (a hand edit, a truncated file) counts as none, and is written over."""
    try:
        record = json.loads(data)
    except ValueError:
        return {}
    valid = isinstance(record, dict) and all(isinstance(record.get(key, 0), int) for key in ("generation", "epoch"))
    return record if valid else {}
