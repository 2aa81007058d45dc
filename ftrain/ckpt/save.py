"""One save, from every rank's point of view: write this rank's files, agree with the others, commit on rank 0.

Every rank writes its own files of the step with ``torch.save`` (exclusive create, each file's size and SHA-256
noted). The ranks then gather those entries on rank 0, which commits the manifest (the step counts from then on) and
applies retention; every rank learns the outcome, so all agree whether the step counts. A failed write never harms
earlier steps: it is reported, agreed on, and the step stays uncommitted (retention later deletes it).

:class:`StepWriter` does this inline. :class:`BackgroundWriter` runs the same on one thread per rank, with a gloo
group of its own so that its collectives never mix with the training loop's; the loop then only pays for the
snapshot, a copy of the state's tensors at the iteration boundary (:func:`snapshot`).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import enum
import functools
import pickle
import queue
import threading
import time
from collections.abc import Callable

import torch
import torch.distributed as dist

from ftrain.ckpt.fence import Fence, Fenced, guarded
from ftrain.ckpt.format import (
    COMMON,
    INCOMPLETE,
    UNSETTLED,
    VERIFIED,
    CorruptCheckpoint,
    FileEntry,
    StepInfo,
    commit,
    decode,
    encode,
    learned_state,
    state_digest,
    unloadable_part,
    verify_step,
    write_file,
)
from ftrain.ckpt.lease import LeaseLost
from ftrain.ckpt.retention import delete_step, retention_plan
from ftrain.ckpt.spool import Spool
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.comm import group
from ftrain.config import CheckpointConfig
from ftrain.errors import did_you_mean

UNLOADABLE_HINT = "hooks and metrics must keep plain data (tensors, numbers, strings, lists, dicts)"
UNPICKLABLE = (pickle.PicklingError, TypeError, AttributeError)
"""What ``torch.save`` raises for an object that cannot be pickled (a lambda, a lock, a local class's object)."""


class Result(enum.StrEnum):
    """What became of one save (a string on the wire: rank 0 broadcasts it as JSON)."""

    COMMITTED = "committed"
    FAILED = "failed"
    """Not committed (a write, the listing or the manifest failed): earlier steps are intact; training goes on."""
    UNLOADABLE = "unloadable"
    """Written state that would not load back: training must stop."""
    FENCED = "fenced"
    """A newer plan or attempt of the run holds the storage or has committed (``fence.py``): this node was cut off
    from the others and must stop."""
    LEASE_LOST = "lease_lost"
    """Another run, or this run started again, has taken the storage's lease (``lease.py``): exit 8."""
    SPOOLED = "spooled"
    """Written to the spool alone, as asked (while the storage is down): the storage has not changed."""


class Target(enum.Enum):
    """Where a save goes (the spool, if there is one, always comes first)."""

    STORAGE = "storage"
    """The storage, each request retried ``checkpoint.retries`` times."""
    TRY = "try"
    """The storage, one attempt per request: saves are failing, and the wait between two tries is their backoff."""
    SPOOL = "spool"
    """The spool alone: the storage is down and its next try is not due."""


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What the ranks agreed on for one save: ``detail`` is the manifest when committed, else why not."""

    result: Result
    step: int
    detail: dict | str
    cpu_s: float = 0.0
    """CPU time this rank's writer thread spent on the save (0 inline, where the loop's blocking time has it)."""


def snapshot(state: object, into: object = None) -> object:
    """A copy of ``state`` that training can no longer change: every tensor copied, every container rebuilt.

    ``into``: an earlier snapshot whose save is over; its tensors of the same place, shape and dtype are reused
    (copied into), since for a large state the page faults of fresh memory cost more than the copy itself.
    """
    if isinstance(state, torch.Tensor):
        if isinstance(into, torch.Tensor) and into.shape == state.shape and into.dtype == state.dtype:
            return into.copy_(state)
        return state.detach().clone()
    if isinstance(state, dict):
        old = into if isinstance(into, dict) else {}
        return {key: snapshot(value, old.get(key)) for key, value in state.items()}
    if isinstance(state, (list, tuple)):
        old = into if isinstance(into, (list, tuple)) and len(into) == len(state) else [None] * len(state)
        return type(state)(snapshot(value, earlier) for value, earlier in zip(state, old, strict=True))
    return state


class StepWriter:
    """Saves of one rank, inline: write, gather on rank 0, commit, retention, share the outcome."""

    def __init__(
        self,
        storage: Storage,
        policy: CheckpointConfig,
        info: group.RankInfo,
        collectives: dist.ProcessGroup | None,
        log: Callable[[str], None],
        spool: Spool | None = None,
    ) -> None:
        """``collectives``: the group the ranks agree in (None: the default group); ``spool``: where every step goes
        first (``spool.py``)."""
        self.storage = storage = guarded(storage)  # every write and delete: the holder's check
        self._one_attempt = storage.with_retries(0)
        self.spool = spool
        self.newest_committed: int | None = None
        """The newest step committed to the storage as far as this rank knows (rank 0: as soon as it commits), which
        a spooled step records as the storage history it continues."""
        self._spool_failing = False
        self.fence = Fence.from_env(storage)
        self.parent: dict | None = None
        """The state the next commit continues, ``{"step", "state_sha256"}``: this holder's previous commit (tried:
        one whose answer was lost may have landed), or the step it resumed from (``lineage.py``); None for a fresh
        start."""
        self.policy = policy
        self._best_metric_checked = False
        self.info = info
        self.collectives = collectives
        self.log = log
        self._steps: dict[int, StepInfo] | None = None
        """Rank 0: the steps in storage, scanned at the first save and then kept up to date by this run's own saves
        and deletions, so that retention needs no listing after every commit."""
        self._undeletable: dict[int, str] = {}
        """Rank 0: steps retention could not delete, and why (said once, and once more when they go)."""
        self.storing = False
        """Whether this rank is busy with the storage for a save now (writing, or rank 0 committing), rather than
        encoding or waiting for its peers: a rank waiting for its save beats only then, so that a stopped peer reads as
        a hang and a slow storage does not."""
        self._listed = False
        """Rank 0: whether a commit has listed its step directory. The first one does: a storage that the ranks do
        not share (node-local directories on several nodes) shows there, once. Later commits trust the writers'
        own successful exclusive creates (a listing is a request per save on S3)."""

    def save(
        self,
        step: int,
        files: dict[str, dict],
        meta: dict | None,
        check_loadable: bool,
        target: Target = Target.STORAGE,
    ) -> Outcome:
        """Write this rank's ``files`` (name to state) of ``step`` to the spool if there is one, then to ``target``;
        ``meta`` (rank 0) goes into the manifest."""
        report = {"entries": {}, "fields": {}, "error": None, "unloadable": False, "fenced": None}
        encoded = {}
        try:
            encoded, report["fields"] = self._encode(files, check_loadable)
        except CorruptCheckpoint as exc:  # state that does not pickle, or would not load back
            report["error"], report["unloadable"] = f"rank {self.info.rank}: {exc}: {UNLOADABLE_HINT}", True
        except Exception as exc:
            report["error"] = f"rank {self.info.rank}: {type(exc).__name__}: {exc}"
        if self.spool is not None:
            unloadable = self._spool(step, encoded, meta, report)
            if target is Target.SPOOL:
                return Outcome(Result.UNLOADABLE if unloadable else Result.SPOOLED, step, "; ".join(unloadable))
        storage = self._one_attempt if target is Target.TRY else self.storage
        self.storing = True
        try:
            if report["error"] is None:
                report["entries"] = self._write(functools.partial(write_file, storage), step, encoded)
        except (LeaseLost, Fenced) as exc:  # the holder's check refused this rank's write: nothing was written
            report["error"], report["fenced"] = f"rank {self.info.rank}: {exc}", [type(exc).__name__, str(exc)]
        except Exception as exc:  # any storage failure: reported, agreed on, never fatal by itself
            report["error"] = f"rank {self.info.rank}: {exc}"
        finally:
            self.storing = False
        reports = group.all_gather_object(report, self.info, self.collectives)
        outcome = None
        if self.info.is_main:
            self.storing = True
            try:
                outcome = self._commit(storage, step, reports, meta)
            except Exception as exc:  # whatever rank 0 meets, every rank hears the same outcome
                outcome = (Result.FAILED, step, f"commit: {type(exc).__name__}: {exc}")
            finally:
                self.storing = False
        result, _, detail = group.broadcast_object(outcome, self.info, self.collectives)
        return Outcome(Result(result), step, detail)

    def _encode(self, files: dict[str, dict], check_loadable: bool) -> tuple[dict[str, bytes], dict]:
        """``files`` encoded, and the manifest fields that come from common.pt. State that cannot be pickled (a
        lambda, a lock) fails alike at every try: CorruptCheckpoint, as for state that would not load back."""
        encoded = {}
        for name, state in files.items():
            try:
                encoded[name] = encode(state)
            except UNPICKLABLE as exc:
                part = unloadable_part(state)
                why = f"{name} cannot be saved ({type(exc).__name__}: {exc})"
                raise CorruptCheckpoint(f"{why} (in {part})" if part else why) from None
        if check_loadable:
            for name, data in encoded.items():
                try:
                    decode(data, name)
                except CorruptCheckpoint as exc:
                    part = unloadable_part(files[name])
                    raise CorruptCheckpoint(f"{exc} (in {part})" if part else str(exc)) from None
        fields = {}
        if COMMON in files:
            common = files[COMMON]
            fields["state_sha256"] = state_digest(learned_state(common))
            if "teacher" in common["ftrain"]:  # plain data: source, step, digest, the teacher's config
                fields["teacher"] = common["ftrain"]["teacher"]
        return encoded, fields

    @staticmethod
    def _write(write: Callable[[int, str, bytes], FileEntry], step: int, encoded: dict[str, bytes]) -> dict:
        """Write ``encoded`` with ``write``: their manifest entries."""
        entries = {}
        for name, data in encoded.items():
            entry = write(step, name, data)
            entries[name] = [entry.size, entry.sha256]
        return entries

    def _spool(self, step: int, encoded: dict[str, bytes], meta: dict | None, report: dict) -> list[str]:
        """Write and commit ``step`` to the spool (see ``spool.py``): why the state of any rank would not load back
        (every rank learns it). A failure leaves the storage's save alone: rank 0 says so once and empties the spool,
        so that no older spooled step is ever taken for the newest."""
        entries, error = None, None
        self.storing = True
        try:
            if report["error"] is None:  # else the save fails anyway
                entries = self._write(self.spool.write, step, encoded)
        except Exception as exc:
            error = f"rank {self.info.rank}: {exc}"
        finally:
            self.storing = False
        mine = report["error"] if report["unloadable"] else None
        spooled = group.all_gather_object([entries, error, mine], self.info, self.collectives)
        errors = [error for _, error, _ in spooled if error]
        unloadable = [why for *_, why in spooled if why]
        if not self.info.is_main or (not errors and any(entries is None for entries, *_ in spooled)):
            return unloadable
        try:
            if not errors:
                files = {name: FileEntry(*entry) for entries, *_ in spooled for name, entry in entries.items()}
                self.spool.commit(step, files, meta | report["fields"], self.newest_committed)
                self._spool_failing = False
                return unloadable
        except Exception as exc:
            errors = [f"commit: {exc}"]
        if not self._spool_failing:
            self.log(
                f"the spool {self.spool.storage.url} failed at step {step} ({'; '.join(errors)}): emptied; saves go "
                "to the storage alone until it works again"
            )
        self._spool_failing = True
        with contextlib.suppress(Exception):
            self.spool.clear()
        return unloadable

    def _commit(self, storage: Storage, step: int, reports: list[dict], meta: dict) -> tuple:
        errors = [report["error"] for report in reports if report["error"]]
        if any(report["unloadable"] for report in reports):
            return (Result.UNLOADABLE, step, "; ".join(errors))
        if fenced := next((report["fenced"] for report in reports if report["fenced"]), None):
            self.log(f"checkpoint step {step} refused: {fenced[1]}")
            return (Result.LEASE_LOST if fenced[0] == LeaseLost.__name__ else Result.FENCED, step, fenced[1])
        if self._steps is None:
            self._steps = {info.step: info for info in scan(storage)}  # may fail: save() reports it
        files = {name: FileEntry(*entry) for report in reports for name, entry in report["entries"].items()}
        fields = {key: value for report in reports for key, value in report["fields"].items()}  # from common.pt
        if not errors:
            if self.fence is not None:
                fields |= self.fence.fields
            parent, self.parent = self.parent, {"step": step, "state_sha256": fields.get("state_sha256")}
            try:  # the manifest's write runs the holder's check (``guarded``)
                manifest = commit(storage, step, files, meta | fields | {"parent": parent}, not self._listed)
                self._listed = True
            except (LeaseLost, Fenced) as exc:  # a newer holder of the storage, or generation of the run, committed
                self.log(f"checkpoint step {step} refused: {exc}")
                self._steps[step] = StepInfo(step, INCOMPLETE)
                return (Result.LEASE_LOST if isinstance(exc, LeaseLost) else Result.FENCED, step, str(exc))
            except Exception as exc:  # the next commit continues this state all the same: a step that did not land
                errors = [f"commit: {exc}"]  # is a parent that lineage passes over
                if (manifest := self._landed(storage, step, files)) is not None:
                    errors = []  # its answer was lost, not the manifest
        if errors:
            if self._steps.get(step, StepInfo(step, INCOMPLETE)).status != UNSETTLED:
                self._steps[step] = StepInfo(step, INCOMPLETE)  # abandoned: retention deletes it
            return (Result.FAILED, step, "; ".join(errors))
        self._steps[step] = StepInfo(step, VERIFIED, sum(entry.size for entry in files.values()), manifest)
        self.newest_committed = step
        self._apply_retention()
        if not self._best_metric_checked:
            with contextlib.suppress(Exception):  # a word to the user: nothing of it may fail a commit
                self._check_best_metric(manifest.get("metrics") or {})
        return (Result.COMMITTED, step, manifest)

    def _check_best_metric(self, recorded: dict) -> None:
        """Say once, at this run's first commit, when ``checkpoint.best_metric`` names no metric the run records (hooks
        add theirs, so the config alone cannot tell): keep_best then keeps no step by it."""
        if not recorded:  # a step with no metrics says nothing: a later one is checked
            return
        self._best_metric_checked = True
        if self.policy.keep_best and self.policy.best_metric not in recorded:
            self.log(
                f"checkpoint.best_metric={self.policy.best_metric} is not a metric of this run"
                f"{did_you_mean(self.policy.best_metric, recorded)}, so keep_best keeps no step by it: use one of "
                f"{', '.join(sorted(recorded))}"
            )

    def _landed(self, storage: Storage, step: int, files: dict[str, FileEntry]) -> dict | None:
        """After a commit that raised, a direct look at ``step``'s manifest, which may have landed though the answer to
        its write was lost: the manifest if it is this commit's. Otherwise the step counts as abandoned; unless the
        look failed as well, when it is left unsettled, which retention never deletes (the next run's scan settles
        it): a committed step must not go on the word of a failed request."""
        try:
            landed = verify_step(storage, step, full=False)
        except Exception:
            self._steps[step] = StepInfo(step, UNSETTLED)
            return None
        ours = {name: {"size": entry.size, "sha256": entry.sha256} for name, entry in files.items()}
        return landed.manifest if landed.ok and landed.manifest["files"] == ours else None

    def _apply_retention(self) -> None:
        """Delete what the retention rules let go; a step that cannot be deleted now is kept and tried again later."""
        policy = self.policy
        doomed = retention_plan(
            self._steps.values(),
            policy.keep_last,
            policy.keep_best,
            policy.best_metric,
            policy.keep_every,
            policy.pinned,
        )
        for step in doomed:
            try:
                delete_step(self.storage, step, self._steps[step].files)
            except Exception as exc:
                if self._undeletable.get(step) != str(exc):  # said once, not at every commit while it lasts
                    self.log(f"retention: checkpoint step {step} could not be deleted (kept, tried again): {exc}")
                self._undeletable[step] = str(exc)
                continue
            del self._steps[step]
            if self._undeletable.pop(step, None) is not None:
                self.log(f"retention: checkpoint step {step} deleted now")


class BackgroundWriter:
    """A :class:`StepWriter` on a thread of its own: saves go in as snapshots, outcomes come back in order."""

    def __init__(self, writer: StepWriter) -> None:
        self.writer = writer
        self._jobs: queue.Queue[tuple | None] = queue.Queue()
        self._outcomes: collections.deque[Outcome] = collections.deque()
        self._done = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="ftrain-checkpoint-writer", daemon=True)
        self._thread.start()

    def submit(
        self, step: int, files: dict[str, dict], meta: dict | None, check_loadable: bool, target: Target
    ) -> None:
        self._jobs.put((step, files, meta, check_loadable, target))

    def ready(self) -> bool:
        """Whether the oldest outcome not yet taken has arrived."""
        with self._done:
            return bool(self._outcomes)

    def take(self, timeout: float) -> Outcome | None:
        """The oldest outcome not yet taken, waiting up to ``timeout`` seconds for it (None if it did not come)."""
        with self._done:
            if not self._outcomes:
                self._done.wait(timeout)
            return self._outcomes.popleft() if self._outcomes else None

    def close(self, timeout: float) -> None:
        """Let the thread finish the saves it was given (up to ``timeout`` seconds) and end."""
        self._jobs.put(None)
        self._thread.join(timeout)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            step = job[0]
            started = time.thread_time()
            try:
                outcome = self.writer.save(*job)
            except Exception as exc:  # the agreement failed (a peer died, the group broke): not committed
                outcome = Outcome(Result.FAILED, step, f"rank {self.writer.info.rank}: {type(exc).__name__}: {exc}")
            outcome = dataclasses.replace(outcome, cpu_s=time.thread_time() - started)
            with self._done:
                self._outcomes.append(outcome)
                self._done.notify_all()
