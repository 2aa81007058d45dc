"""Hang detection from heartbeats: a rank whose heartbeat ``seq`` stays unchanged for too long."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ftrain import procfs
from ftrain.heartbeat import Heartbeat

HANG_FLOOR = 30.0
HANG_FACTOR = 10.0
QUIET_PHASES = ("done", "preempted")
"""Phases after which a rank only exits: never a hang."""


class HangWatch:
    """Times every rank's heartbeat ``seq``; when one has been silent too long, names the hung rank: a stopped
    (T) or uninterruptible (D) process if there is one, else the rank silent longest."""

    def __init__(self, timeout: float | None, startup_grace: float, ranks: int) -> None:
        self.timeout = timeout
        self.startup_grace = startup_grace
        self.ranks = ranks
        self.longest = 0.0
        """Longest gap seen between two heartbeats of a rank after start-up, over all attempts."""

    def restart(self, now: float) -> None:
        self.launched = now
        self.started = False
        self.changed: dict[int, tuple[int, float]] = {}

    def limit(self) -> float:
        if self.timeout is not None:
            return self.timeout
        return max(HANG_FLOOR, HANG_FACTOR * self.longest)

    def check(self, beats: dict[int, Heartbeat], now: float) -> Hang | None:
        """Record progress in ``beats``; return the hang if there is one."""
        for rank, beat in beats.items():
            seq, since = self.changed.get(rank, (None, now))
            if beat.seq != seq:
                if self.started and seq is not None:
                    self.longest = max(self.longest, now - since)
                self.changed[rank] = (beat.seq, now)
        if not self.started:
            self.started = len(beats) >= self.ranks and all(b.phase != "start" for b in beats.values())
        if not self.started:
            if now - self.launched <= self.startup_grace:
                return None
            starting = [rank for rank, beat in beats.items() if beat.phase == "start"]
            rank = min(starting) if starting else None
            return Hang(rank, "start", round(now - self.launched, 1), self.startup_grace, ranks_seen=len(beats))
        active = [(self.changed[rank][1], rank) for rank, beat in beats.items() if beat.phase not in QUIET_PHASES]
        if not active:
            return None
        since, rank = min(active)
        if now - since <= self.limit():
            return None
        states = {r: process_state(b.pid) for r, b in sorted(beats.items())}
        # the others wait for it in a collective and may have been silent longer: name a stopped rank if any
        rank = next((r for r, state in states.items() if state in ("T", "t", "D")), rank)
        beat = beats[rank]
        seconds, limit = round(now - self.changed[rank][1], 1), round(self.limit(), 1)
        processes = {str(r): state for r, state in states.items()}
        return Hang(rank, beat.phase, seconds, limit, iteration=beat.iteration, processes=processes)


@dataclass
class Hang:
    """A rank silent for longer than the limit, or a start-up that took longer than the grace (``ranks_seen`` set)."""

    rank: int | None
    phase: str
    seconds: float
    limit: float
    iteration: int | None = None
    processes: dict[str, str] | None = None
    """Each rank's process state letter: a stopped (T) or uninterruptible (D) one is named as the hung rank."""
    ranks_seen: int | None = None

    def fields(self) -> dict:
        """For the event log: the fields that apply (``rank`` always, None if no rank was to blame)."""
        return {key: value for key, value in dataclasses.asdict(self).items() if value is not None or key == "rank"}

    def cause(self) -> str:
        return "killed: start-up hung" if self.ranks_seen is not None else f"killed: rank {self.rank} hung"

    def describe(self) -> str:
        if self.ranks_seen is not None:
            return f"not every rank got past start-up within {self.limit:g} s (--startup-grace)"
        return f"rank {self.rank} silent for {self.seconds} s in phase {self.phase} (limit {self.limit} s)"


def process_state(pid: int) -> str:
    """The kernel's state letter for ``pid`` (R running, S sleeping, T stopped, ...), or ``gone``."""
    fields = procfs.stat_fields(pid)
    return fields[0] if fields else "gone"
