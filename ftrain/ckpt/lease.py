"""One run per storage: the lease ``<storage>/LEASE.json``, held by a run while it lives (docs/supervision.md, "One run
per storage").

Owns the record: the run id, its ``generation`` (``ftrain/identity.py``), the ``ttl``, and one entry per renewing
process (host, pid, start time, boot id, pid namespace, ``renewed_at``). Promises:
- a second run is refused while any entry lives: until ``renewed_at + ttl`` and, by the storage's own clock, while
  the record was written within ``ttl`` (no host's clock is trusted to agree with another's); on the entry's own
  host (same name, boot id and pid namespace) a dead pid frees it at once and a live one holds it past the expiry;
- a run id names one start of a run: a second start of it is refused while the first runs on this host, and takes
  the next generation from another host's (only the supervisors of one run's nodes share a generation: ``shared``);
- every change is a compare-and-swap of the record read (``cas.py``): of two racing processes one wins;
- the generation only grows (a release keeps the record; a record deleted by hand restarts after the newest
  generation that committed); on several nodes a plan's maker takes the next one (``advance``), the others
  ``follow`` it; a holder that finds a newer generation has lost the storage for good (``lost``; ``fence.py`` then
  refuses its writes, its supervisor stops the workers: exit 8).
Torch-free: the supervisor holds the lease for its workers; unsupervised, rank 0 does (``claim.py``).
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import reprlib
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ftrain.ckpt import cas
from ftrain.ckpt.format import newest_generation
from ftrain.ckpt.storage import Storage
from ftrain.errors import EXIT_STORAGE_HELD, UserError
from ftrain.identity import Identity, restore_environ, saved_environ
from ftrain.procfs import Process
from ftrain.values import is_number, is_whole

LEASE = "LEASE.json"
FENCE = "FENCE.json"
"""The newest (generation, attempt) that committed (``fence.py``): where a lease record that was deleted starts."""
TTL_ENV = "FTRAIN_LEASE_TTL"
"""Seconds a lease lives after its last renewal, where ``TTL`` does not suit (a storage slow to answer)."""
TTL = 60.0
"""Seconds a lease lives after its last renewal; renewed every third of that."""


SHORTEST, LATEST = 1e-3, 1e11
"""The shortest ttl a lease takes, and the latest time it may name (epoch seconds, the year 5138): a record out of
those bounds is damaged; ``FTRAIN_LEASE_TTL`` is held to them too."""


def ttl_from_env() -> float:
    """``TTL``, or the seconds ``FTRAIN_LEASE_TTL`` sets: UserError for one that is not a positive number."""
    text = os.environ.get(TTL_ENV)
    if not text:
        return TTL
    try:
        ttl = float(text)
    except ValueError:
        ttl = math.nan
    if not (SHORTEST <= ttl <= LATEST):
        raise UserError(
            f"{TTL_ENV}={text!r} must be a number of seconds from {SHORTEST:g} to {LATEST:g}, e.g. {TTL_ENV}={TTL:g}"
        )
    return ttl


class LeaseHeld(Exception):
    """Another run, alive, holds the storage; the message names it and when its lease ends, in one line."""


class LeaseLost(LeaseHeld):
    """Another run took the storage after this one held it (a newer generation): this run must stop writing."""


class Advanced(Exception):
    """The lease is no longer at the generation a process meant to advance from (``Lease.advance``)."""


@dataclass(frozen=True)
class Entry:
    """One renewing process of the run holding the lease."""

    process: Process
    renewed_at: float
    since: float = 0.0
    """When this process took or joined the lease (epoch seconds, its host's clock): the holder's age, for humans."""

    def alive(self, ttl: float, now: float) -> bool:
        """Seen running on this host, or (where that cannot be seen) renewed within ``ttl``, by a clock no more than
        ``ttl`` ahead of this host's (a renewal in the future tells nothing: the storage's clock decides, ``_live``)."""
        running = self.process.running()
        return running if running is not None else now < self.renewed_at + ttl and self.renewed_at <= now + ttl


@dataclass(frozen=True)
class Record:
    run_id: str
    generation: int
    ttl: float
    entries: tuple[Entry, ...]

    @property
    def expires_at(self) -> float:
        return max((entry.renewed_at for entry in self.entries), default=0.0) + self.ttl

    def live(self, now: float) -> list[Entry]:
        return [entry for entry in self.entries if entry.alive(self.ttl, now)]

    def encode(self) -> bytes:
        body = {
            "run_id": self.run_id,
            "generation": self.generation,
            "ttl": self.ttl,
            **({"expires_at": round(self.expires_at, 3), "expires": _when(self.expires_at)} if self.entries else {}),
            "holders": [
                {**dataclasses.asdict(e.process), "renewed_at": round(e.renewed_at, 3), "since": round(e.since, 3)}
                for e in self.entries
            ],
        }
        return json.dumps(body, indent=1).encode()

    @classmethod
    def decode(cls, data: bytes) -> Record:
        """The record in ``data``; ValueError naming the field that is missing, of another type or out of range (a
        generation below 1 or a float would make every commit look superseded; a time past year 5000)."""
        body = _typed(json.loads(data), dict)
        holders = _field(body, "holders", lambda value: _typed(value, list))
        entries = []
        for index in range(len(holders)):
            where = f"holders[{index}]."
            holder = _field(holders, index, lambda value: _typed(value, dict), "holders")
            entries.append(
                Entry(
                    Process(
                        _field(holder, "host", _text, where),
                        _field(holder, "pid", _whole, where),
                        _field(holder, "start", _whole, where),
                        _field(holder, "boot", _text, where),
                        _field(holder, "pidns", _text, where),
                    ),
                    _field(holder, "renewed_at", _seconds, where),
                    _field(holder, "since", _seconds, where, default=0.0),
                )
            )
        generation = _field(body, "generation", lambda value: _whole(value, low=1))
        ttl = _field(body, "ttl", lambda value: _seconds(value, low=SHORTEST))
        return cls(_field(body, "run_id", _text), generation, ttl, tuple(entries))


def _field(data: dict | list, key: str | int, check: Callable[[Any], Any], where: str = "", default: Any = None) -> Any:
    """``check(data[key])`` (of ``default`` if given and it is missing); ValueError naming the field (``where`` +
    ``key``) if it is missing or ``check`` fails."""
    name = f"{where}[{key}]" if isinstance(key, int) else f"{where}{key}"
    try:
        value = data[key] if default is None or key in data else default
    except (KeyError, IndexError):
        raise ValueError(f"{name} is missing") from None
    try:
        return check(value)
    except (TypeError, ValueError) as wrong:
        raise ValueError(f"{name}: {wrong}") from None


def _typed(value: object, kind: type) -> object:
    if not isinstance(value, kind):
        raise TypeError(f"{reprlib.repr(value)} is not a {kind.__name__}")
    return value


def _text(value: object) -> str:
    return _typed(value, str)


def _whole(value: object, low: int = 0) -> int:
    """An int (not a bool, not a float) of ``low`` or more, below 2**63."""
    if not is_whole(value, low) or value >= 2**63:
        raise ValueError(f"{reprlib.repr(value)} is not a whole number of {low} or more")
    return value


def _seconds(value: object, low: float = 0.0) -> float:
    """A number of seconds (epoch or a duration) from ``low`` to ``LATEST``: every time ``_when`` can print."""
    if not is_number(value) or not low <= value <= LATEST:
        raise ValueError(f"{reprlib.repr(value)} is not a number of seconds from {low} to {LATEST:g}")
    return float(value)


class Lease:
    """The lease of ``storage`` for run ``run_id``, held by this process: ``hold`` takes it and keeps renewing it
    from a thread until ``release``. Storage failures while renewing are logged and retried, never raised."""

    def __init__(
        self,
        storage: Storage,
        run_id: str,
        log: Callable[[str], None],
        ttl: float = TTL,
        plain_writes: bool = False,
        shared: bool = False,
        follows: bool = False,
    ) -> None:
        """``plain_writes``: hold it even on a storage without conditional writes (``cas.require_atomic``);
        ``shared``: held by the supervisors of several nodes of one run, which join each other's entries. Else one
        process holds it for its run (one node's supervisor, an unsupervised run's rank 0), and a live entry of its
        run id is another start of the run: refused where it is seen running (this host), taken over elsewhere (it
        may be the run's old holder on a host it left; if it still runs, the fence stops it). ``follows``: a
        supervisor on several nodes, whose workers take their generation from the plan: a newer generation of its
        own run is a newer plan, which it follows, not a loss."""
        self.storage = storage
        self.plain_writes = plain_writes
        self.shared = shared or follows
        self.follows = follows
        self.run_id = run_id
        self.log = log
        self.ttl = ttl
        self.process = Process.current()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._environ: dict[str, str | None] = {}
        self.generation: int | None = None
        """The generation this run holds, once taken."""
        self.took = False
        """Whether this process took its generation (a new holder, the maker of a plan), rather than join it."""
        self.lost: str | None = None
        """Why the storage is lost to another run, once it is (for good)."""

    def acquire(
        self, advance: bool = False, expected: int | None = None, stop: threading.Event | None = None
    ) -> str | None:
        """Take the lease, or, ``shared``, join this run's while another of its nodes holds it (the nodes of one run
        share a generation; ``advance``: the maker of a new plan, which takes the next one for them all, only from
        generation ``expected`` if given, else ``Advanced``); LeaseHeld if another run holds it, or another start of
        this run on this host; LeaseLost if a newer generation took it after this process held it. A line saying so
        if this took over a lease with holders, else None.

        A run id may outlive its processes (a batch job's id kept across a requeue, the same command run again), so
        a process that finds none of its run alive takes the next generation, as another run would: whatever the old
        ones still have in flight is then refused at commit (``fence.Fence``). Shared, entries of other hosts that
        only look expired get a third of the ttl first: nodes cut off from the storage by an outage renew by then,
        and are joined. (A requeued job whose old processes on other hosts still renew joins them: SLURM kills
        those.) ``stop``: a renewal, which gives up once it is set (a write refused because ``release`` dropped the
        entry meanwhile must not write it back)."""
        looked = None
        while stop is None or not stop.is_set():
            now = time.time()
            current = read_record(self.storage)
            record, version = current if current is not None else (None, None)
            newer = record is not None and self.generation is not None and record.generation != self.generation
            if newer and not (self.follows and record.run_id == self.run_id):
                raise LeaseLost(lost_message(self.storage, record, self.run_id, self.generation))
            if advance and expected is not None and (record is None or record.generation != expected):
                raise Advanced(record.generation if record is not None else 0)
            live = self._live(record, now) if record is not None else []
            if record is not None and record.run_id != self.run_id and live:
                raise LeaseHeld(self._held_message(record, live))
            ours = record is not None and record.run_id == self.run_id
            others = tuple(e for e in live if e.process != self.process) if ours else ()
            if others and self.generation is None and not self.shared and (here := _seen_running(others)):
                raise LeaseHeld(self._held_message(record, here))  # the same run id launched twice on this host
            joins = ours and (self.generation is not None or (bool(others) and self.shared))
            if ours and not joins and self.shared and version != looked and _unseen(record):
                # its other hosts' entries only look expired: after an outage they renew within a third of the
                # ttl (``_keep``). Look again then, and join them if they did, rather than fence them off
                looked = version
                time.sleep(self.ttl / 3)
                continue
            if joins and not advance:
                generation = record.generation
            elif record is not None:  # a new holder, or a new plan: the next generation
                generation = record.generation + 1
            else:  # none, or deleted: this process's generation, else the one after the newest committed
                fenced = read_fence(cas.read(self.storage, FENCE)).get("generation", 0)
                generation = self.generation or max(fenced, newest_generation(self.storage)) + 1
            since = next((e.since for e in record.entries if e.process == self.process), now) if ours else now
            mine = Entry(self.process, now, since)
            new = Record(self.run_id, generation, self.ttl, (*(others if joins else ()), mine))
            if stop is not None and stop.is_set():
                return None  # released since this read, which may be the record after the drop: no write back
            try:
                cas.write(self.storage, LEASE, new.encode(), version)
            except cas.Conflict:
                continue
            if self.generation is None or advance:
                self.took = advance or not joins
            gone = record is None and self.generation is not None  # held, and its record deleted since
            self.generation = generation
            if gone:
                return (
                    f"the lease {self.storage.where(LEASE)} was gone (deleted under the run, maybe with the storage's "
                    f"checkpoints): written again, generation {generation}"
                )
            replaced = record is not None and bool(record.entries) and not joins and (not ours or bool(others))
            return self._taken_message(record) if replaced else None
        return None

    def renew(self) -> str | None:
        """Renew this process's entry (``acquire``); once another run took it, a line saying so, once (``lost``)."""
        if self.lost is not None:
            return None
        try:
            return self.acquire(stop=self._stop)
        except LeaseLost as lost:
            self.lost = str(lost)
            return self.lost

    def hold(self, advance: bool = False) -> str | None:
        """``acquire`` (``advance``: see there), then renew every ``ttl / 3`` from a daemon thread; returns what
        ``acquire`` did. This process's environment names the run and its generation from then on
        (``Identity.env``): its own commits and its child processes' are checked against them (``fence.Fence``)."""
        cas.require_atomic(self.storage, self.plain_writes)  # a lease rests on conditional writes
        taken = self.acquire(advance)
        self._environ = saved_environ()  # as ``release`` leaves it
        self._name_environ()
        self._thread = threading.Thread(target=self._keep, name="ftrain-lease", daemon=True)
        self._thread.start()
        return taken

    def current(self) -> int:
        """The generation the lease has now (one read; 0: none)."""
        current = read_record(self.storage)
        return current[0].generation if current is not None else 0

    def advance(self, expected: int) -> tuple[int, bool]:
        """Take the next generation after ``expected`` for this run, its live processes kept: this process makes a new
        plan of it. The lease's generation, and whether this process took it (not if the lease had moved on from
        ``expected``: another process of the run took the next one first, and makes the plan)."""
        try:
            self.acquire(advance=True, expected=expected)
        except Advanced as moved:
            return moved.args[0], False
        self._name_environ()
        return self.generation, True

    def _name_environ(self) -> None:
        """This process's environment names the run and the generation it holds: its commits and its child
        processes' are checked against them (``fence.Fence``)."""
        os.environ.update(Identity(self.run_id, self.generation).env())

    def run(self, body: Callable[[Lease], int], refused: Callable[[str], None], advance: bool = False) -> int:
        """``body(self)`` while holding the lease (``hold``: its child processes are this run), then release it; if
        another run holds it (or takes it before ``body`` is done with the lease: ``advance``), ``refused`` gets the
        one-line reason and this returns ``EXIT_STORAGE_HELD``."""
        try:
            taken = self.hold(advance)
        except LeaseHeld as held:
            refused(str(held))
            return EXIT_STORAGE_HELD
        if taken:
            self.log(taken)
        try:
            return body(self)
        except LeaseHeld as held:
            refused(str(held))
            return EXIT_STORAGE_HELD
        finally:
            self.release()

    def release(self) -> None:
        """Stop renewing and drop this process's entry (the whole object with the run's last entry), so the same
        command again starts at once. A failure is logged: the lease then lapses after its ``ttl``."""
        self._stop.set()
        restore_environ(self._environ)  # as before ``hold``
        if self._thread is not None:
            self._thread.join(timeout=self.ttl / 3)  # a renewal stuck in a hanging request: its write is a CAS too
        try:
            self._drop()
        except Exception as error:
            self.log(f"could not release the lease {self.storage.where(LEASE)} ({error}); it lapses in {self.ttl:g} s")

    def check(self) -> None:
        """LeaseHeld if another run, alive, holds the lease (a worker whose supervisor holds it for its run)."""
        current = read_record(self.storage)
        if current is not None and current[0].run_id != self.run_id and (live := self._live(current[0], time.time())):
            raise LeaseHeld(self._held_message(current[0], live))

    def _keep(self) -> None:
        """Renew until stopped; 4 times as often while the storage fails, with one line when that starts and ends."""
        failing_since = None
        while not self._stop.wait(self.ttl / 3 if failing_since is None else self.ttl / 12):
            try:
                message = self.renew()
            except Exception as error:
                if failing_since is None:
                    failing_since = time.monotonic()
                    self.log(f"renewing the lease {self.storage.where(LEASE)} failed ({error}); retrying")
                continue
            if failing_since is not None:
                self.log(f"renewed the lease again after {time.monotonic() - failing_since:.0f} s of failures")
                failing_since = None
            if message:
                self.log(message)

    def _drop(self) -> None:
        """This process's entry out of the record; the record stays, with its generation, when that was the last
        (the next run takes the generation after it)."""
        while True:
            current = read_record(self.storage)
            ours = current is not None and current[0].run_id == self.run_id
            if not ours or (current[0].generation != self.generation and not self.follows):
                return  # not this process's record any more: a newer generation's, which it must not touch
            record, version = current
            keep = tuple(e for e in record.live(time.time()) if e.process != self.process)
            try:
                cas.write(self.storage, LEASE, dataclasses.replace(record, entries=keep).encode(), version)
                return
            except cas.Conflict:
                continue

    def _live(self, record: Record, now: float) -> list[Entry]:
        """The entries of ``record`` that hold the lease: ``Record.live``; and where none is by the times the
        entries carry, those not seen gone on this host, if the storage's own clock says the record was written
        within its ``ttl`` (``cas.age``, one request). An entry's time is its host's clock: one running behind this
        host's would make a live lease look expired, and a second run take the storage from the first."""
        live = record.live(now)
        unseen = [entry for entry in record.entries if entry.process.running() is not False]
        if live or not unseen:
            return live
        age = cas.age(self.storage, LEASE)  # negative past the ttl: a time set ahead (a copy that kept it, a touch)
        return unseen if age is not None and -record.ttl < age < record.ttl else []

    def _held_message(self, record: Record, live: list[Entry]) -> str:
        holder = max(live, key=lambda e: e.renewed_at)
        ends, now = record.expires_at, time.time()
        if ends > now + 2 * record.ttl:  # renewed in this host's future: the storage's clock found it renewed
            end = (
                f"was renewed at {_when(ends - record.ttl)} by its host's clock, ahead of this one's; the storage's "
                "clock says it is still renewed"
            )
        elif ends < now and holder.process.running():  # not renewed, but alive here (stopped, say): never taken from it
            end = f"ran out at {_when(ends)}, but its process still exists on this host and keeps it"
        elif ends < now:  # by its host's clock; the storage's own clock says it was renewed within its time to live
            end = f"ran out at {_when(ends)} by its host's clock, but the storage's clock says it is still renewed"
        else:
            end = f"ends at {_when(ends)} unless renewed"
        since = f" since {_when(holder.since)}" if holder.since else ""
        if record.run_id == self.run_id:
            return (
                f"storage {self.storage.url} is held by another start of run {record.run_id} "
                f"({holder.process.describe()}{since}): two launches share the run id {record.run_id} (FTRAIN_RUN_ID "
                f"or torchrun's --rdzv-id); stop that one first, or give this one another storage"
            )
        return (
            f"storage {self.storage.url} is held by another run ({record.run_id}, {holder.process.describe()}{since}): "
            f"its lease {end}; stop that run first, or use another storage"
        )

    def _taken_message(self, record: Record) -> str:
        now = time.time()

        def fate(entry: Entry) -> str:
            if entry.process.running() is False:
                return f"{entry.process.describe()} is gone"
            ends = entry.renewed_at + record.ttl
            if ends < now:
                return f"the lease of {entry.process.describe()} expired at {_when(ends)}"
            if entry.renewed_at > now + record.ttl:
                return (
                    f"{entry.process.describe()} last renewed it at {_when(entry.renewed_at)} by its host's clock, "
                    "ahead of this one's; by the storage's clock it expired"
                )
            return f"{entry.process.describe()} held it until {_when(ends)}: if it still runs, it commits nothing more"

        holders = ", ".join(fate(entry) for entry in record.entries)
        started = "an earlier start of run" if record.run_id == self.run_id else "run"
        return f"took over the lease of {self.storage.url} from {started} {record.run_id}: {holders or 'no holder'}"


def read_fence(current: tuple[bytes, str] | None) -> dict:
    """The fence record ``FENCE.json`` (``fence.py``) read as ``cas.read`` gives it; none, or an unreadable one (a hand
    edit, a truncated file, an older ftrain's), is ``{}``, and is written over."""
    try:
        record = json.loads(current[0]) if current is not None else {}
    except (ValueError, RecursionError):
        return {}
    valid = isinstance(record, dict) and all(type(record.get(key)) is int for key in ("generation", "attempt"))
    return record if valid else {}


def _seen_running(entries: tuple[Entry, ...]) -> list[Entry]:
    """Those of ``entries`` seen running on this host."""
    return [entry for entry in entries if entry.process.running()]


def _unseen(record: Record) -> bool:
    """Whether ``record`` has entries this host cannot tell gone (another host's, another pid namespace's)."""
    return any(entry.process.running() is None for entry in record.entries)


def lost_message(storage: Storage, record: Record, run_id: str, generation: int) -> str:
    if record.run_id == run_id:  # started again while this process still ran (requeued, paused, cut off)
        return (
            f"the lease of {storage.url} was taken by a newer start of run {run_id} (generation {record.generation}; "
            f"this one's is {generation}): this process lost the storage and commits nothing more"
        )
    return (
        f"the lease of {storage.url} was taken by run {record.run_id} (generation {record.generation}; this run's is "
        f"{generation}): this run lost the storage and commits nothing more"
    )


def read_record(storage: Storage) -> tuple[Record, str] | None:
    try:
        current = cas.read(storage, LEASE)
    except IsADirectoryError:
        raise UserError(
            f"{storage.where(LEASE)} is a directory where ftrain keeps the storage's lease, a file: if no run uses "
            "this storage, delete that directory"
        ) from None
    if current is None:
        return None
    try:
        return Record.decode(current[0]), current[1]
    except (ValueError, TypeError, RecursionError) as wrong:  # RecursionError: arrays in arrays thousands deep
        unparsed = isinstance(wrong, (json.JSONDecodeError, UnicodeDecodeError, RecursionError))
        reason = "not JSON" if unparsed else str(wrong)
        raise UserError(
            f"{storage.where(LEASE)} is not a lease ftrain can read ({reason}): if no run uses this storage, delete "
            "that file"
        ) from None


def saving_now(storage: Storage) -> str | None:
    """A line naming the run that holds ``storage`` now, if one does: its newest incomplete step may be a save in
    flight, not one cut short."""
    try:
        found = read_record(storage)
    except UserError:
        return None
    live = found[0].live(time.time()) if found else []
    if not live:
        return None
    holder = max(live, key=lambda entry: entry.renewed_at).process.describe()
    return f"run {found[0].run_id} ({holder}) holds this storage now: an incomplete step may be its save in flight"


def _when(epoch: float) -> str:
    return datetime.datetime.fromtimestamp(epoch, datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
