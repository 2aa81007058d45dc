"""The restart policy: whether a failed attempt is started again, and after how long.

``--max-restarts`` bounds the restarts; the crash loop (``--crash-loop`` restarts in a row that committed no new
step) stops a run that cannot get anywhere; an attempt that completed no iteration is followed by a back-off
(``--backoff-initial``, doubled for each further one, at most ``--backoff-max``). Attempts ended by an unreachable
storage are not judged here: the supervisor waits for the storage instead (``outage.py``).
"""

from __future__ import annotations

from ftrain.supervise.attempt import Attempt
from ftrain.supervise.options import EXIT_CRASH_LOOP, EXIT_MAX_RESTARTS, SupervisorOptions
from ftrain.supervise.outcome import Event, Outcome, newest_step


class RestartPolicy:
    def __init__(self, options: SupervisorOptions) -> None:
        self.options = options
        self.restarts = 0
        self.best_committed: int | None = None
        """The newest step any attempt of this run committed or resumed from."""
        self._no_commit = 0
        self._no_progress = 0
        self._unstarted = 0
        """Restarts since the newest attempt that started from a step (or since the first attempt)."""

    def judge(self, attempt: Attempt) -> Outcome | float:
        """After ``attempt`` failed: the ending of the run, or the seconds to back off before the restart it counts.
        A step it started from that is newer than any known was committed by the newest attempt before it that
        started (one that crashed before it restored a step commits nothing), whose heartbeats missed it (a save that
        landed as it crashed): the loop counts from that attempt on. The step it started from is no new commit of its
        own; a step a regroup inside it resumed from was its own commit."""
        if self._newer(attempt.started_from):
            self._no_commit, self.best_committed = self._unstarted, attempt.started_from
        new_commit = self._newer(attempt.committed)
        if new_commit:
            self.best_committed = attempt.committed
        self._no_commit = 0 if new_commit or self.restarts == 0 else self._no_commit + 1
        self._no_progress = 0 if attempt.progressed else self._no_progress + 1
        self._unstarted = 0 if attempt.started or self.restarts == 0 else self._unstarted + 1
        if self.restarts >= self.options.max_restarts:
            return Outcome(Event.MAX_RESTARTS, EXIT_MAX_RESTARTS, f"giving up after {self.restarts} restarts")
        if self.options.crash_loop and self._no_commit >= self.options.crash_loop:
            return Outcome(
                Event.CRASH_LOOP,
                EXIT_CRASH_LOOP,
                f"crash loop: {self._no_commit} restarts in a row committed no new checkpoint "
                f"({newest_step(self.best_committed)}); fix the cause above and run the same command again",
            )
        self.restarts += 1
        if not self._no_progress:
            return 0.0
        return min(self.options.backoff_max, self.options.backoff_initial * 2 ** (self._no_progress - 1))

    def _newer(self, step: int | None) -> bool:
        return step is not None and (self.best_committed is None or step > self.best_committed)
