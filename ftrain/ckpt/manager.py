"""A rank's checkpoints: resume at the start, and saves at iteration boundaries, coordinated across ranks.

Resuming is ``resume.py``; one save is ``save.py``; when to save is ``schedule.py``. This module acts on what the
ranks agreed for each save: a committed step (hooks hear of it), a failed one (training goes on, and the newest state
is tried again as soon as the failed save has settled, then after waits that double up to ``RETRY_DELAY_MAX``; in
between, saves on the schedule go to the spool alone, so that a crash while the storage is down loses no more than
usual), an unloadable one (stop). A start that finds the storage down counts as a failed save. A save that must
commit (the last one of a run, a stop, or one with more unsaved work than ``checkpoint.max_unsaved``) holds training
until it does: it is retried with backoff (``retry.OUTAGE``), a line every ``WAIT_LINES`` seconds, for up to the
storage wait (``FTRAIN_STORAGE_WAIT``, which ``ftrain supervise`` sets from ``--storage-wait``), then the rank ends
with ``StorageUnavailable``: nothing committed is lost.

With ``checkpoint.async_save`` (the default) a save is a snapshot handed to the rank's writer thread, and up to
``MAX_IN_FLIGHT`` may be in flight; without it, the rank writes and agrees inline, a plain ``torch.save`` per file.
"""

from __future__ import annotations

import collections
import dataclasses
import os
import time
from collections.abc import Callable

from ftrain.ckpt import arithmetic, resume
from ftrain.ckpt.fence import guarded
from ftrain.ckpt.format import COMMON, STATE_FORMAT, recorded_metrics, shard_name
from ftrain.ckpt.lease import LeaseLost
from ftrain.ckpt.resume import Checkpointable, CheckpointError
from ftrain.ckpt.retention import promised
from ftrain.ckpt.retry import OUTAGE, WaitLines
from ftrain.ckpt.save import BackgroundWriter, Outcome, Result, StepWriter, Target, snapshot
from ftrain.ckpt.schedule import DEFAULT_STORAGE_WAIT, STORAGE_WAIT_ENV, SaveSchedule
from ftrain.ckpt.spool import Spool
from ftrain.ckpt.storage import NoBucket, Storage, StorageUnavailable
from ftrain.comm import group
from ftrain.config import Config
from ftrain.errors import UserError
from ftrain.lifeline import SUPERVISOR_ENV
from ftrain.values import parse_amount

MAX_IN_FLIGHT = 2
"""Saves handed to the writer thread and not yet settled: with two, it may fall one save behind without blocking
the loop."""
WAIT_BEAT = 0.5
"""Seconds between two calls of ``while_waiting`` while a rank waits for a save (its heartbeat: not a hang)."""
RETRY_DELAY_MAX = 8.0
"""The longest wait between a failed save's end and the next try of the storage while training goes on (the first
comes as soon as the failed one has settled, then after 1, 2, 4 s...): each try is requests to the storage, which back
to back took 13 s of the two cores during two 60 s outages (``launch/bench_chaos.py``)."""
QUICK_CHECK_RETRIES = 1
"""Retries of a supervised start's first request to a storage it may do without (resuming from the spool): a start
while the storage is down would otherwise wait out every retry (3 s with the default ``checkpoint.retries``)."""


@dataclasses.dataclass(frozen=True)
class Failing:
    """Saves that failed in a row: since when, when the newest settled (monotonic), how many, and why."""

    since: float
    last: float
    count: int
    why: str


class Checkpointer:
    def __init__(
        self, config: Config, info: group.RankInfo, log: Callable[..., None], robot: dict | None = None
    ) -> None:
        """``log(message, every_rank=False)``: a line for the run's log; ``robot``: the identity of the robot trained
        (``ftrain.policy.robot.identity``), for the manifests and the resume check."""
        self.config = config
        self.robot = robot
        self.info = info
        self.log = log
        storage, self._down = _open_storage(config)
        self.storage = guarded(storage)
        """The run's storage, every write and delete checked against the holder's lease (``fence.guarded``)."""
        if info.distributed and self.storage.url.startswith("memory://"):
            raise UserError(
                f"storage {self.storage.url} lives inside one process, but this run has {info.world_size} ranks: "
                "use a local path, file:// or s3://"
            )
        background = config.checkpoint.async_save
        collectives = group.new_group(config.dist_timeout, info) if background else None
        self.spool = Spool.open(config, self.storage, info)
        self._writer = StepWriter(self.storage, config.checkpoint, info, collectives, log, self.spool)
        self._background = BackgroundWriter(self._writer) if background else None
        policy = config.checkpoint
        self.schedule = SaveSchedule(
            parse_amount("checkpoint.interval", policy.interval, auto=True),
            policy.max_overhead,
            parse_amount("checkpoint.max_unsaved", policy.max_unsaved),
            time.monotonic(),
            promised=lambda step: promised(step, policy.keep_every, policy.pinned),
        )
        self.storage_wait = float(os.environ.get(STORAGE_WAIT_ENV, DEFAULT_STORAGE_WAIT))
        self.committed_step: int | None = None
        self.config_change: str | None = None
        """What ``allow_config_change`` let change at the resume, in words (``ftrain.ckpt.changes``)."""
        self.on_commit: Callable[[int, dict], None] = lambda step, manifest: None
        self.while_waiting: Callable[[], None] = lambda: None
        self.stopping: Callable[[], bool] = lambda: False
        """Whether this rank was asked to stop: a held save then gives up after the try it is making."""
        self._pending: collections.deque[tuple[int, dict, float]] = collections.deque()
        """(step, snapshot, seconds the loop blocked for it) of the saves handed to the writer thread whose outcome
        has not been acted on yet."""
        self._spare: list[dict] = []
        """Snapshots whose saves are over: the next snapshots copy into their memory."""
        now = time.monotonic()
        self._failing = None if self._down is None else Failing(now, now, 1, str(self._down))
        """Saves failing in a row; None while the newest settled save committed."""
        self._failure_lines = WaitLines()
        self._checked_loadable = False
        self.arithmetic = group.all_gather_object(arithmetic.describe(), info)
        """Every rank's arithmetic (``arithmetic.describe``), in rank order."""
        self.last_blocking_s = 0.0
        self.last_commit_s = 0.0
        """Seconds from the start of the newest committed save to its commit (what the console tells)."""
        self._static_meta = {  # computed once: package metadata lookups cost ~10 ms
            "state_format": STATE_FORMAT,
            "world_size": info.world_size,
            "envs_per_rank": config.env.num_envs,
            "env_id": config.env.id,
            "config_hash": config.training_hash(robot),
            **({"robot": robot} if robot is not None else {}),
            "config": config.public_dict(),
            "versions": arithmetic.versions(("ftrain", "torch", "rsl-rl-lib", "gymnasium", "mujoco")),
            "arithmetic": arithmetic.by_rank(self.arithmetic),
        }

    def restore(self, trainer: Checkpointable) -> int | None:
        """Load the step to start from into ``trainer`` (see ``resume.py``); the step, or None for a fresh start."""
        resumed = resume.restore(
            trainer, self.config, self.info, self.storage, self.log, self.robot, self.spool, self._down, self.arithmetic
        )
        if resumed.own:
            self.committed_step = self._writer.newest_committed = resumed.committed
            self.schedule.committed = (resumed.committed, time.monotonic())
        if resumed.step is not None:
            self._writer.parent = {"step": resumed.step, "state_sha256": resumed.digest}
        self._static_meta["world_sizes"] = resumed.world_sizes
        if resumed.origin is not None:
            self._static_meta[resume.ORIGIN] = resumed.origin
        self.config_change = resumed.config_change
        return resumed.step

    def votes(self, iteration: int) -> tuple[bool, bool, bool, bool]:
        """This rank's votes after ``iteration``, which the ranks sum: save now, save to the storage (not to the
        spool alone), hold (train no further until that save commits), and busy (``MAX_IN_FLIGHT`` saves in flight,
        none settled: another save would wait for the oldest, on a storage that hangs for as long as its requests'
        deadlines; a save due then is left to the next boundary, unless it holds, or retention keeps its step: a
        pinned step or a milestone waits for the oldest, which on a hanging storage pauses training for as long as
        that save's deadlines).

        While saves fail, and nothing is in flight: to the storage once the failed save's wait is over, or when more
        work than ``checkpoint.max_unsaved`` is unsaved (hold); to the spool alone when the schedule says, and for the
        first save of a start (it is waited for, see ``save``: not on a storage that just failed)."""
        self._settle(MAX_IN_FLIGHT)  # the outcomes that have arrived
        now = time.monotonic()
        due = self.schedule.due(iteration, now)
        busy = len(self._pending) >= MAX_IN_FLIGHT and not self.schedule.promised(iteration)
        if self._failing is None:
            return due, due, False, busy
        count = self._failing.count
        delay = 0.0 if count < 2 else min(RETRY_DELAY_MAX, 2.0 ** min(count - 2, 8))
        hold = self.schedule.over_bound(iteration, now)
        idle = not self._pending
        store = idle and (hold or (self._checked_loadable and now - self._failing.last >= delay))
        spool = idle and self.spool is not None and (due or not self._checked_loadable)
        return store or spool, store, hold, busy

    def save(self, trainer: Checkpointable, wait: bool = False, hold: bool = False, store: bool = True) -> None:
        """Save the state of ``trainer`` as step ``trainer.iteration``.

        In the background: snapshot now, the writer thread does the rest. Waited for: with ``wait``, and the first
        save of a run (it checks that what is saved loads back). ``hold``: train no further until this state is
        committed (the save that ends a run, or too much unsaved work): retry until it is, or StorageUnavailable.
        Without ``store`` (and without ``hold``), the state goes to the spool alone.
        """
        # a slot for this save (waiting for the oldest), whose outcome decides its target
        self._settle(MAX_IN_FLIGHT - 1)
        if not (store or hold or self.spool is None):
            self._submit(trainer, wait, Target.SPOOL)
        else:
            self._submit(trainer, wait, Target.STORAGE if self._failing is None else Target.TRY)
        if hold:
            self._hold(trainer)

    def close(self) -> None:
        """Wait for the saves in flight and act on their outcomes."""
        self._settle(0)

    def shutdown(self) -> None:
        """Let the writer thread end: at once if nothing is in flight, else after its saves (bounded by the
        collectives' timeout, as a dead peer fails them)."""
        if self._background is not None:
            self._background.close(timeout=self.config.dist_timeout + 5)

    def _submit(self, trainer: Checkpointable, wait: bool, target: Target) -> None:
        started = time.perf_counter()
        step = trainer.iteration
        if step == self.committed_step or step in (pending for pending, *_ in self._pending):
            return
        self.schedule.started(step, time.monotonic())
        files = {shard_name(self.info.rank): trainer.rank_state()}
        meta = None
        if self.info.is_main:
            files[COMMON] = trainer.common_state()
            meta = self._meta(trainer)
        first = not self._checked_loadable
        self._checked_loadable = True
        if self._background is None:
            outcome = self._writer.save(step, files, meta, first, target)
            self.last_blocking_s = time.perf_counter() - started
            self._act_on(outcome, self.last_blocking_s)
            return
        copy = snapshot(files, self._spare.pop() if self._spare else None)
        self._background.submit(step, copy, meta, first, target)
        self.last_blocking_s = time.perf_counter() - started
        self._pending.append((step, copy, self.last_blocking_s))
        if wait or first:
            self._settle(0)

    def _hold(self, trainer: Checkpointable) -> None:
        """Retry the state of ``trainer`` until it is committed: with backoff, heartbeats, and a line at the first try
        and then every ``WAIT_LINES`` seconds."""
        self._settle(0)
        tries, lines = 0, WaitLines()
        while self.committed_step != trainer.iteration:
            since, why = self._failing.since, self._failing.why
            waited = time.monotonic() - since
            if waited > self.storage_wait or self.stopping():
                stop = ", then a stop came" if waited <= self.storage_wait else ""
                step = self.committed_step
                newest = "no step is committed yet" if step is None else f"the newest committed step is {step}"
                raise StorageUnavailable(
                    f"the storage {self.storage.url} took no checkpoint for {waited:.0f} s ({why}){stop}; {newest}: "
                    "run the same command again once it takes writes again (it answers, has room, lets this run write)"
                )
            delay = OUTAGE.delay(tries)
            iterations, seconds = self.schedule.unsaved(trainer.iteration, time.monotonic())
            if lines.due():
                self.log(
                    f"training held at step {trainer.iteration}: {iterations} iterations ({seconds:.0f} s) unsaved, "
                    f"saves failing for {waited:.0f} s ({why}); next try in {delay:.1f} s, it goes on as soon as "
                    f"one lands (at most {self.storage_wait:g} s)"
                )
            self._pause(delay)
            tries += 1
            self._submit(trainer, wait=True, target=Target.TRY)

    def _pause(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self.while_waiting()
            time.sleep(min(WAIT_BEAT, left))

    def _meta(self, trainer: Checkpointable) -> dict:
        return {
            **self._static_meta,
            "iteration": trainer.iteration,
            "metrics": recorded_metrics(trainer.metrics),
        }

    def _settle(self, keep: int) -> None:
        """Act on the agreed outcomes of the oldest saves in flight until at most ``keep`` are left (and on any
        that are already there: the newest committed step is known as soon as possible)."""
        while self._pending and (len(self._pending) > keep or self._background.ready()):
            _, copy, blocked = self._pending.popleft()
            while (outcome := self._background.take(WAIT_BEAT)) is None:
                if self._writer.storing:  # waiting for the storage is work; waiting for a peer is not
                    self.while_waiting()
            self._spare.append(copy)  # the writer is done with it
            self._act_on(outcome, blocked)

    def _act_on(self, outcome: Outcome, blocked: float) -> None:
        """Every rank hears the same outcome and says so: a failure and a recovery are each one line per rank."""
        step, detail, now = outcome.step, outcome.detail, time.monotonic()
        self.schedule.settled(step, outcome.result is Result.COMMITTED, blocked + outcome.cpu_s)
        if outcome.result is Result.LEASE_LOST:
            raise LeaseLost(detail)
        if outcome.result is Result.UNLOADABLE:  # a hook's or metric's state: the user's to fix, a restart saves alike
            raise UserError(detail)
        if outcome.result is Result.FENCED:
            raise CheckpointError(detail)
        if outcome.result is Result.SPOOLED:
            return
        if outcome.result is Result.COMMITTED:
            if self._failing is not None:
                since = now - self._failing.since
                self.log(f"checkpoint step {step} committed: saves work again after {since:.0f} s", every_rank=True)
            self._failing = None
            self.committed_step = step
            self.last_commit_s = now - self.schedule.committed[1]  # from when its state was taken
            self.on_commit(step, detail)
            return
        first = self._failing is None
        count = 1 if first else self._failing.count + 1
        self._failing = Failing(now if first else self._failing.since, now, count, detail)
        if self._failure_lines.due(always=first):
            iterations, seconds = self.schedule.unsaved(step, now)
            bound = self.config.checkpoint.max_unsaved
            then = f"training goes on and retries; it holds past checkpoint.max_unsaved={bound}"
            if step >= self.config.iterations:  # nothing left to train on: only the retries
                then = "training is done, and the run retries this last step until it commits"
            self.log(
                f"checkpoint step {step} not committed, earlier steps intact ({detail}); {iterations} iterations "
                f"({seconds:.0f} s) unsaved, {then}",
                every_rank=True,
            )


def _open_storage(config: Config) -> tuple[Storage, StorageUnavailable | None]:
    """The run's storage, and why it does not answer (None: it does). Under a supervisor a storage that does not
    answer is opened all the same, after ``QUICK_CHECK_RETRIES``: the run may resume from the spool, and the
    supervisor holds the lease, so no other run writes there. A missing bucket is bad input, but not under a
    supervisor: it reached the bucket before it launched the run, so it was deleted since (the supervisor decides)."""
    url, options, retries = config.storage.url, config.storage.options, config.checkpoint.retries
    supervised = bool(os.environ.get(SUPERVISOR_ENV))
    may_spool = supervised and config.checkpoint.spool
    storage = Storage.open(url, options, retries, check_bucket=False)
    try:
        storage.with_retries(min(retries, QUICK_CHECK_RETRIES) if may_spool else retries).check()
        return storage, None
    except NoBucket as missing:
        if not supervised:
            raise
        down = StorageUnavailable(missing.gone)  # the supervisor reached it before it launched this attempt
    except StorageUnavailable as error:
        down = error
    if not may_spool:
        raise down
    return storage, down
