"""Waiting out an unreachable checkpoint storage, or a full local disk.

A worker that cannot reach the storage ends with exit 7 (``StorageUnavailable``): an infrastructure fault, not bad
input. The supervisor then probes the storage itself, with backoff and a line every ``WAIT_LINES`` seconds, and
restarts the workers once it answers; such restarts count neither towards ``--max-restarts`` nor the crash loop. After
``--storage-wait`` seconds it gives up with exit 7; nothing committed is lost. A storage never reached since the command
started may be misnamed: waited for 5 minutes, not an hour (``WAITS``). An attempt that finds it unusable again before
training an iteration continues the same wait and backs off first (``AGAIN``), even where the probe passes (a storage
that lists but refuses writes): never a restart loop. A full local disk is waited for alike: after any failed attempt
the supervisor asks ``short_of_space`` (room for one more checkpoint and a margin), whose answer the workers could not
write on that disk. The supervisor's own looks at the storage's head (``head_of``, ``start_of``: the step a start or a
rerun resumes from) wait at most ``NEWEST_WITHIN`` seconds. Imports the storage layer and the standard library.
"""

from __future__ import annotations

import contextlib
import errno
import shutil
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from ftrain.ckpt.format import CHECKPOINTS, StepInfo, human_size, verify_step
from ftrain.ckpt.lineage import history
from ftrain.ckpt.retry import OUTAGE, Backoff, WaitLines
from ftrain.ckpt.spool import SPOOL
from ftrain.ckpt.steps import resolve_checkpoint_url, scan
from ftrain.ckpt.storage import NoBucket, Storage, StorageError, StorageUnavailable
from ftrain.config import AUTO, Config, StorageConfig
from ftrain.errors import EXIT_USAGE, NO_SPACE, UserError
from ftrain.progress import Progress, duration
from ftrain.redact import Url
from ftrain.supervise.events import EventLog
from ftrain.supervise.options import EXIT_STORAGE_WAIT
from ftrain.supervise.outcome import Event, Outcome

T = TypeVar("T")

SPACE_MARGIN = 1 << 20
"""Bytes of free disk a run needs besides its next checkpoint: logs, heartbeats, the lease."""
WAITS = (300.0, 3600.0)
"""``--storage-wait``'s default: for a storage that has not answered once since the command started (a wrong URL or
endpoint is then likelier than an outage, and an hour is long to learn that), and for one that answered and went
away."""
NEWEST_WITHIN = 5.0
"""Seconds the run's start (its world size) and its ending wait for the storage to name its newest step."""
AGAIN = Backoff(1.0, 60.0)
"""Before restarting into a storage that answers the probe but failed the last attempt too, before it trained an
iteration: the probe tells nothing then, and each attempt costs a start-up."""


@dataclass
class _Outage:
    started: float
    """When the wait began, by the wait's clock."""
    since: str
    """The same, as a time of day for the console."""
    tries: int = 0
    """Probes that found it unusable."""
    fruitless: int = 0
    """Attempts since it began that found it unusable again before they trained an iteration."""


class StorageWait:
    def __init__(
        self,
        storage: StorageConfig,
        limit: float | None,
        events: EventLog,
        sleep: Callable[[float], None],
        clock: Callable[[], float] = time.monotonic,
        log_dir: Path | None = None,
    ) -> None:
        """``limit``: seconds to wait (None: ``WAITS``) by ``clock``; ``sleep``: the supervisor's sleep, which ends the
        run on a signal; ``log_dir``: where the workers write their logs and heartbeats (its disk must have room)."""
        self.storage = storage
        self.log_dir = log_dir
        self.explicit_limit = limit
        self.events = events
        self.sleep = sleep
        self.clock = clock
        self.reached = False
        """Whether the storage has answered since the command started (its lease was taken, or a probe answered)."""
        self._outage: _Outage | None = None
        """The last wait, which an attempt that ends on the storage again without training continues."""

    @property
    def limit(self) -> float:
        return self.explicit_limit if self.explicit_limit is not None else WAITS[self.reached]

    def retrying(self, action: Callable[[], int], end: Callable[[Outcome], int]) -> int:
        """``action()`` once the storage answers, and again whenever it raises StorageUnavailable; ``end(ending)`` if
        it does not answer within the limit. A storage not reached yet gets one probe first: one line if it does not
        answer, instead of a line for each retry of the action's first request."""
        ending = None if self.reached else self(None)
        while ending is None:
            try:
                return action()
            except StorageUnavailable as error:
                ending = self(str(error))
        return end(ending)

    def __call__(self, why: str | None, again: bool = False) -> Outcome | None:
        """Probe until the storage answers (None), or the ending of the run: it did not within the limit, or what it
        answers no waiting fixes (access denied; a missing bucket, unless the run reached it before: then it was
        deleted under the run, and is waited for). ``why``: what found it unreachable (None: nothing
        yet, this is a first look); ``again``: the attempt since the last wait trained nothing before it found the
        storage unusable too: the wait goes on from there, and backs off before the restart even if the probe passes."""
        url = self.storage.url  # a Url: printed and recorded without its credentials
        if not again or self._outage is None:
            self._outage = _Outage(self.clock(), time.strftime("%H:%M:%S"))
        outage, lines = self._outage, WaitLines(self.clock)
        progress = Progress(sys.stderr)  # on a terminal, while it sleeps between tries: how long it has waited
        if why is not None:
            self._waiting(url, why, lines)
        while True:
            try:
                problem = probe(self.storage.url, self.storage.options, self.log_dir)
            except NoBucket as missing:
                if not self.reached:
                    return Outcome(Event.USAGE, EXIT_USAGE, str(missing))
                problem = missing.gone  # deleted under the run: the spool keeps its newest steps until it is back
            except UserError as error:
                return Outcome(Event.USAGE, EXIT_USAGE, str(error))
            waited = self.clock() - outage.started
            if problem is None and not again:
                if why is not None or outage.tries:
                    back = f"the storage is usable again after {waited:.0f} s"
                    self.events("storage_back", back, waited=round(waited, 2))
                self.reached = True
                return None
            if why is None and not outage.tries:
                self._waiting(url, problem, lines)
            if waited > self.limit:
                return Outcome(
                    Event.STORAGE_DOWN,
                    EXIT_STORAGE_WAIT,
                    f"the storage {url} was not usable for {self.limit:g} s ({problem or why}); nothing committed is "
                    "lost: run the same command again once it is usable again",
                )
            delay = AGAIN.delay(outage.fruitless) if again else OUTAGE.delay(outage.tries)
            if lines.due() or again:
                problem = problem or "it answers, but the last attempt could not use it before training an iteration"
                print(
                    f"ftrain supervise: storage {url} not usable since {outage.since} ({problem}); next try in "
                    f"{delay:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )
            limit = duration(self.limit)
            progress.show(f"ftrain supervise: waiting for storage {url}: {duration(waited)} of at most {limit}...")
            try:
                self.sleep(delay)
            finally:
                progress.clear()
            outage.fruitless += again
            outage.tries += not again
            again = False

    def disk_full(self) -> str | None:
        """Why the local disks the run writes to lack room (``short_of_space``), or None: asked after a failed attempt,
        whose workers may have been unable to say so (their error files are written to the same disk)."""
        try:
            storage = Storage.open(self.storage.url, self.storage.options, retries=0)
            return short_of_space(storage, storage.list_dirs("checkpoints") if storage.is_local else [], self.log_dir)
        except (StorageError, UserError):
            return None

    def newest(self, known: int | None) -> int | None:
        """The step a rerun resumes from, or ``known`` (the workers' word) where the storage does not answer within
        ``NEWEST_WITHIN``: their heartbeats may miss a commit made as they were stopped, and a scheduler's grace
        after a stop is short."""
        answered, head = head_of(self.storage)
        if not answered:
            return known
        return head.step if head is not None else None

    def holds(self, step: int) -> bool:
        """Whether the storage holds ``step`` committed and intact (its files match its manifest's sizes and SHA-256,
        as a resume checks them); False also where it does not answer."""
        try:
            return verify_step(Storage.open(self.storage.url, self.storage.options, retries=0), step).ok
        except (StorageError, UserError):
            return False

    def _waiting(self, url: Url, why: str, lines: WaitLines) -> None:
        """The wait's first line (the next comes ``WAIT_LINES`` seconds later): a storage never reached may be a
        wrong URL or endpoint."""
        if self.reached:
            line = f"{why}; waiting up to {self.limit:g} s for it"
        else:
            line = (
                f"storage {url} has not answered since this command started ({why}): check its URL and endpoint; "
                f"waiting up to {self.limit:g} s (--storage-wait)"
            )
        self.events("storage_wait", line, storage=url, cause=why)
        lines.due(always=True)


def head_of(storage: StorageConfig) -> tuple[bool, StepInfo | None]:
    """Whether the storage answered within ``NEWEST_WITHIN`` seconds, and the step a rerun resumes from: the head of
    its history, its files checked by size (None: no step)."""
    return _within(lambda: _head(storage))


def start_of(config: Config) -> tuple[bool, tuple[int, dict] | None]:
    """Whether the storage answered within ``NEWEST_WITHIN`` seconds, and (step, manifest) of the step a start
    resumes from: the head of the storage's history, else ``resume=``'s step (None: a fresh start). UserError for
    bad input found on the way (a ``resume=`` step that does not verify, a bucket that does not exist), which no
    wait mends: the start ends with it before anything is made."""

    def look() -> tuple[int, dict] | UserError | None:
        try:
            if (head := _head(config.storage)) is not None:
                return head.step, head.manifest or {}
        except UserError as error:
            return error
        if config.resume == AUTO:
            return None
        try:
            _, step, manifest = resolve_checkpoint_url(config.resume, config.storage.options, log=lambda line: None)
        except UserError as error:  # unless the workers may go on from the spool instead (``resume.py``)
            spooled = Path(config.log_dir) / SPOOL / CHECKPOINTS
            return None if spooled.is_dir() and any(spooled.iterdir()) else error
        return step, manifest

    answered, start = _within(look)
    if isinstance(start, UserError):
        raise start
    return answered, start


def _head(storage: StorageConfig) -> StepInfo | None:
    infos = scan(Storage.open(storage.url, storage.options, retries=0))
    line = history(infos).line
    return next((info for info in infos if line and info.step == line[0]), None)


def _within(look: Callable[[], T]) -> tuple[bool, T | None]:
    """``look()`` in a thread, waited for ``NEWEST_WITHIN`` seconds at most: whether it answered, and what."""
    answers: list[T] = []

    def answer() -> None:
        with contextlib.suppress(StorageError, UserError):
            answers.append(look())

    looking = threading.Thread(target=answer, name="ftrain-newest-step", daemon=True)
    looking.start()
    looking.join(NEWEST_WITHIN)
    return bool(answers), answers[0] if answers else None


def probe(url: str, options: dict | None = None, log_dir: Path | None = None) -> str | None:
    """None if the storage at ``url`` answers (it opens, and its checkpoints can be listed) and the local disks the run
    writes to have room (``short_of_space``), else why not, in one line, for an infrastructure fault worth waiting
    for; UserError for one that waiting cannot fix."""
    try:
        storage = Storage.open(url, options, retries=0)
        return short_of_space(storage, storage.list_dirs("checkpoints"), log_dir)
    except StorageError as error:
        return str(error)


def short_of_space(storage: Storage, steps: list[str], log_dir: Path | None) -> str | None:
    """Why a run cannot go on for lack of local disk, or None: a local storage's disk needs room for one more
    checkpoint (the largest of the newest three ``steps``) and ``SPACE_MARGIN``, the log directory's the margin, and a
    write of the margin must succeed in each (a quota, or no inode left, shows only then)."""
    checkpoint = "a checkpoint and its logs): free space there, or keep fewer checkpoints (checkpoint.keep_last)"
    needs: dict[Path, tuple[int, str]] = {}  # path: bytes it needs, and what for and the fix
    if storage.is_local:
        sizes = (sum(storage.list_files(f"checkpoints/{step}").values()) for step in steps[-3:])
        needs[Path(storage.root) / "checkpoints"] = (max(sizes, default=0) + SPACE_MARGIN, checkpoint)
    if log_dir is not None:
        needs.setdefault(log_dir, (SPACE_MARGIN, "the run's logs and heartbeats): free space there"))
    for path, (need, fix) in needs.items():  # on one disk, the storage's need (the larger) covers the log directory's
        existing = next(parent for parent in (path, *path.parents) if parent.exists())
        free = shutil.disk_usage(existing).free
        short = (
            f"{human_size(free)} free where the run needs {human_size(need)}" if free < need else _write_fails(existing)
        )
        if short:
            return f"no space left for {path}: {short} ({fix}"
    return None


def _write_fails(directory: Path) -> str | None:
    """How a write of ``SPACE_MARGIN`` bytes in ``directory`` fails for lack of space (None: it does not); UserError
    where it may not write at all (no waiting fixes that)."""
    try:  # a file without a name (O_TMPFILE; else unlinked at once): a process killed here leaves nothing behind
        with tempfile.TemporaryFile(dir=directory, prefix=".ftrain-space-probe-") as file:
            file.write(bytes(SPACE_MARGIN))
            file.flush()
    except OSError as error:
        if error.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            raise UserError(f"cannot write in {directory} ({error.strerror}): check its permissions") from None
        return f"a {human_size(SPACE_MARGIN)} write fails: {error.strerror}" if error.errno in NO_SPACE else None
    return None
