"""When a rank saves, and how much unsaved work it may carry while the storage is down.

``checkpoint.interval``: every N iterations (an integer), every so much training time (``"90s"``, ``"5m"``), or
``"auto"``: the interval in seconds follows the measured cost of a save so that saving takes at most
``checkpoint.max_overhead`` of the training time (CheckFreq, FAST'21, tunes checkpoint frequency online the same
way). The cost of a save is what it takes from training: the time the loop blocked for it (the snapshot) plus the
CPU time the writer thread spent on it (on a busy machine every second it computes is a second training does not
get). Waiting for storage costs no CPU and is not counted.

``checkpoint.max_unsaved``: how much work since the newest committed step (iterations, or seconds of training) is
acceptable while saves fail; past it, training pauses until the newest state is committed.

A step that retention promises to keep (``checkpoint.pinned``, a multiple of ``checkpoint.keep_every``) is saved
whatever the interval; a save the schedule asked for and did not get (the writer busy with two saves) comes at the
next boundary.

Clocks differ between ranks, so the schedule only votes: every rank sums the votes in the iteration's all-reduce
and all save together when any rank voted. Nothing here decides what is trained.
"""

from __future__ import annotations

from collections.abc import Callable

from ftrain.values import Amount

STORAGE_WAIT_ENV = "FTRAIN_STORAGE_WAIT"
"""Seconds a held save waits for the storage before the rank gives up (``ftrain supervise --storage-wait`` sets it)."""
DEFAULT_STORAGE_WAIT = 3600.0
MIN_AUTO_INTERVAL = 2.0
"""Seconds: ``auto`` saves at most this often, however cheap a save is (each is a few requests to the storage)."""
MAX_AUTO_INTERVAL = 600.0
"""Seconds: ``auto`` saves at least this often, however costly a save is."""


class SaveSchedule:
    """One rank's view of when to save: the interval, the cost of recent saves, the newest committed state."""

    def __init__(
        self,
        interval: Amount | None,
        max_overhead: float,
        max_unsaved: Amount,
        now: float,
        promised: Callable[[int], bool] = lambda step: False,
    ) -> None:
        """``interval``: None for ``auto``; ``now``: a monotonic clock reading at the start of training; ``promised``:
        whether retention keeps a step (pinned, a milestone), which is then saved whatever the interval."""
        self.interval = interval
        self.promised = promised
        self.owed = False
        """The schedule asked for a save that has not started since (``due``)."""
        self.max_overhead = max_overhead
        self.max_unsaved = max_unsaved
        self.cost = 0.0
        """Seconds of training the most recent save took (see the module doc); 0 before the first."""
        self.last_save = now
        self.taken: dict[int, float] = {}
        """Step -> when its state was taken, for the saves not settled yet."""
        self.committed = (None, now)
        """(step, when its state was taken) of the newest committed state; the start of training for none."""

    def seconds(self) -> float | None:
        """The interval in seconds, for a time-based or automatic schedule."""
        if self.interval is None:
            return min(MAX_AUTO_INTERVAL, max(MIN_AUTO_INTERVAL, self.cost / self.max_overhead))
        return self.interval.seconds

    def due(self, iteration: int, now: float) -> bool:
        """This rank's vote: is a save due after ``iteration``? Also when one was due at an earlier boundary and none
        started since (``owed``), and at a step that retention keeps."""
        if self.interval is not None and self.interval.iterations is not None:
            self.owed |= iteration % self.interval.iterations == 0
        else:
            self.owed |= now - self.last_save >= self.seconds()
        return self.owed or self.promised(iteration)

    def started(self, step: int, now: float) -> None:
        self.owed = False
        self.last_save = now
        self.taken[step] = now

    def settled(self, step: int, committed: bool, cost: float) -> None:
        self.cost = cost
        taken = self.taken.pop(step, None)
        if committed and taken is not None:
            self.committed = (step, taken)

    def unsaved(self, iteration: int, now: float) -> tuple[int, float]:
        """Iterations and seconds of work since the newest committed state."""
        step, taken = self.committed
        return iteration - (step or 0), now - taken

    def over_bound(self, iteration: int, now: float) -> bool:
        return self.max_unsaved.exceeded_by(*self.unsaved(iteration, now))
