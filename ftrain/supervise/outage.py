"""Waiting out an unreachable checkpoint storage.

A worker that cannot reach the storage ends with exit 7 (``StorageUnavailable``): an infrastructure fault, not bad
input. The supervisor then probes the storage itself, with backoff (a line at the first probe, then every
``WAIT_LINES`` seconds), and starts the workers again once it answers; such restarts count neither towards
``--max-restarts`` nor the crash loop. After ``--storage-wait`` seconds it gives up with exit 7; nothing committed is
lost. The workers get the same wait (``FTRAIN_STORAGE_WAIT``)
for a save they must commit.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable

from ftrain.ckpt.storage import Storage, StorageError, StorageUnavailable, WaitLines, backoff
from ftrain.config import StorageConfig
from ftrain.errors import EXIT_USAGE, UserError
from ftrain.redact import display_url
from ftrain.supervise.events import EventLog
from ftrain.supervise.options import EXIT_STORAGE_WAIT
from ftrain.supervise.outcome import Outcome

PROBES = (1.0, 5.0)
"""Seconds between two probes: the first, and the longest (doubling, with jitter). Short: every second between the
storage's return and the next probe is lost to the whole run, and a probe is one request."""


class StorageWait:
    def __init__(self, storage: StorageConfig, limit: float, events: EventLog, sleep: Callable[[float], None]) -> None:
        """``limit``: seconds to wait; ``sleep``: the supervisor's sleep, which ends the run on a signal."""
        self.storage = storage
        self.limit = limit
        self.events = events
        self.sleep = sleep

    def retrying(self, action: Callable[[], int], end: Callable[[Outcome], int]) -> int:
        """``action()``, again once the storage answers whenever it raises StorageUnavailable; ``end(ending)`` if it
        does not answer within the limit."""
        while True:
            try:
                return action()
            except StorageUnavailable as error:
                ending = self(str(error))
                if ending is not None:
                    return end(ending)

    def __call__(self, why: str) -> Outcome | None:
        """Probe until the storage answers (None), or the ending of the run: it did not within the limit, or what it
        answers no waiting fixes (a bucket gone, access denied)."""
        url = display_url(self.storage.url)  # for people and records; the probe gets the real one
        started, since, tries, lines = time.monotonic(), time.strftime("%H:%M:%S"), 0, WaitLines()
        self.events("storage_wait", f"{why}; waiting up to {self.limit:g} s for it", storage=url, cause=why)
        while True:
            try:
                problem = probe(self.storage.url, self.storage.options)
            except UserError as error:
                return Outcome("usage", EXIT_USAGE, str(error))
            waited = time.monotonic() - started
            if problem is None:
                self.events("storage_back", f"the storage answers again after {waited:.0f} s", waited=round(waited, 2))
                return None
            if waited > self.limit:
                return Outcome(
                    "storage_down",
                    EXIT_STORAGE_WAIT,
                    f"the storage {url} did not answer for {self.limit:g} s ({problem}); nothing committed is lost: "
                    "run the same command again once it is back",
                )
            delay = backoff(PROBES[0], tries, PROBES[1])
            if lines.due():
                print(
                    f"ftrain supervise: storage {url} unreachable since {since} ({problem}); next try in {delay:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )
            self.sleep(delay)
            tries += 1


def probe(url: str, options: dict | None = None) -> str | None:
    """None if the storage at ``url`` answers (it opens, and its checkpoints can be listed), else why not, in one
    line, for an infrastructure fault worth waiting for; UserError for one that waiting cannot fix."""
    try:
        Storage.open(url, options, retries=0).list_dirs("checkpoints")
    except StorageError as error:
        return str(error)
    return None
