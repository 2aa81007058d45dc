"""The supervisor's accounting across attempts: the step each resumed from, iterations lost and downtime per
recovery (``resumed`` and ``recovered`` events), and their totals for the summary."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ftrain.heartbeat import Heartbeat
from ftrain.supervise.attempt import Attempt


@dataclass
class Failure:
    """A failure not yet recovered from: when it was detected and how many iterations had completed."""

    detected: float
    completed: int


class Ledger:
    def __init__(self, ranks: int, events: Callable[..., None]) -> None:
        self.ranks = ranks
        """Ranks on this node: an attempt has progressed when every one of them completed an iteration."""
        self.events = events
        self.lost = 0
        self.downtime = 0.0
        self.pending: Failure | None = None

    def failed(self, completed: int, now: float) -> None:
        """An attempt failed at ``now`` after ``completed`` iterations (several failures before a recovery are one)."""
        if self.pending is None:
            self.pending = Failure(now, completed)
        else:
            self.pending.completed = max(self.pending.completed, completed)

    def observe(self, attempt: Attempt, beats: dict[int, Heartbeat], now: float) -> None:
        """Track completed iterations and commits; log the resumed step and the first iteration after a failure."""
        if not beats:
            return
        for beat in beats.values():
            # a checkpoint/done/preempted beat keeps the iteration of the rollout; its committed step may be newer
            attempt.completed = max(attempt.completed, beat.iteration, beat.committed_step or 0)
            if beat.committed_step is not None:
                attempt.committed = max(beat.committed_step, attempt.committed or 0)
        if not attempt.seen:
            past_start = [beat for beat in beats.values() if beat.phase != "start"]  # restored by now
            if not past_start:
                return
            attempt.seen = True
            attempt.resumed = min(past_start, key=lambda beat: beat.rank).resumed_step
            self.events("resumed", attempt=attempt.plan.attempt, step=attempt.resumed)
        base = attempt.resumed or 0
        if attempt.progressed or len(beats) < self.ranks:
            return
        if all(beat.iteration > base for beat in beats.values()):
            attempt.progressed = True
            if self.pending is not None:
                lost = max(0, self.pending.completed - base)
                downtime = now - self.pending.detected
                self.lost += lost
                self.downtime += downtime
                self.pending = None
                start = "the start (no checkpoint yet)" if attempt.resumed is None else f"step {attempt.resumed}"
                self.events(
                    "recovered",
                    f"attempt {attempt.plan.attempt}: recovered from {start} ({lost} iterations lost, {downtime:.1f} s "
                    "down)",
                    attempt=attempt.plan.attempt,
                    step=attempt.resumed,
                    lost=lost,
                    downtime=round(downtime, 3),
                )
