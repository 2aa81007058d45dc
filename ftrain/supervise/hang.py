"""Hang detection from heartbeats, phase by phase, so that slow work is not called a hang and a hang in fast work is
caught in seconds.

A heartbeat names the ``Phase`` its rank is in, which lasts until the rank's next heartbeat (``seq``). Each phase is
timed on its own, as NVIDIA's resiliency extension times its sections, over all attempts: its limit is
``max(HANG_FLOOR, HANG_FACTOR x its longest time so far)``, and ``--startup-grace`` while it has not been seen. The
ranks time their phases themselves and report the longest in their heartbeats (``Heartbeat.longest``): a phase of a
few milliseconds seldom meets one of the supervisor's polls, and unseen it would keep the start-up grace, so that a
rank stopped while its peer waits in such a phase would go unnoticed.
Start-up (from the launch until every rank is past ``start``) and the first iteration after it get
``--startup-grace`` too, and are not counted in the phases' times: what they take depends on what the attempt starts
from (a fresh start, a resume from a large checkpoint on slow storage), which no earlier attempt predicts, and a slow
first iteration must not make a later hang in the same phase wait for ten times as long.
``--hang-timeout SECONDS`` is one fixed limit for every phase after start-up instead.

The group is hung when every rank still working has been in its phase for longer than that phase's limit. Ranks wait
for each other in collectives, so a rank that works on and beats (rank 0 holding a save while storage is down) while
the others wait silently is slow work, not a hang; and a stopped rank stops the others at their next collective.
Silence counts only while the supervisor watches: a supervisor that did not run for ``ABSENT_AFTER`` or more (stopped
with its workers, a paused VM, a host asleep) is ``credit``ed the gap: its workers get their full limit again.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ftrain import procfs
from ftrain.heartbeat import Heartbeat, Phase

HANG_FLOOR = 5.0
HANG_FACTOR = 10.0
QUIET_PHASES = (Phase.DONE, Phase.PREEMPTED)
"""Phases after which a rank only exits: never a hang."""
ABSENT_AFTER = HANG_FLOOR
"""A gap between two of the supervisor's polls this long is its own absence, not a slow poll on a busy machine."""
UNTIMED_PHASES = (Phase.CLOSING,)
"""Phases limited by the start-up grace only: once per attempt, and rank 0's differs from its peers' (it alone commits
the last save and flushes the trackers), so no earlier close, and no peer's quick one, says how long this one takes."""


class HangWatch:
    """Times every rank's phases; when the group has been silent too long, names the hung rank: a stopped (T) or
    uninterruptible (D) process if there is one, else the rank silent longest."""

    def __init__(self, timeout: float | None, startup_grace: float, ranks: int) -> None:
        self.timeout = timeout
        self.startup_grace = startup_grace
        self.ranks = ranks
        self.longest: dict[Phase, float] = {}
        """The longest time a rank spent in each phase, after its first iteration, over all attempts."""

    def restart(self, now: float) -> None:
        self.launched = now
        self.started = False
        self.changed: dict[int, tuple[Heartbeat, float]] = {}
        """Each rank's latest heartbeat and when it was first seen."""
        self.first: dict[int, int] = {}
        """Each rank's first iteration in this attempt: the iteration of the first heartbeat seen past ``start``."""

    def credit(self, seconds: float) -> None:
        """The supervisor was away for ``seconds``: what it last saw is dated as if seen ``seconds`` later."""
        self.launched += seconds
        self.changed = {rank: (beat, seen + seconds) for rank, (beat, seen) in self.changed.items()}

    def limit(self, rank: int, beat: Heartbeat) -> float:
        """How long ``rank`` may stay in the phase of ``beat``."""
        if self.timeout is not None:
            return self.timeout
        longest = self.longest.get(beat.phase)
        if longest is None or beat.phase in UNTIMED_PHASES or self._first_iteration(rank, beat):
            return self.startup_grace
        return max(HANG_FLOOR, HANG_FACTOR * longest)

    def check(self, beats: dict[int, Heartbeat], now: float) -> Hang | None:
        """Record progress in ``beats``; return the hang if there is one."""
        for rank, beat in beats.items():
            self._observe(rank, beat, now)
        if not self.started:
            self.started = len(beats) >= self.ranks and all(b.phase != Phase.START for b in beats.values())
        if not self.started:
            if now - self.launched <= self.startup_grace:
                return None
            starting = [rank for rank, beat in beats.items() if beat.phase == Phase.START]
            rank = min(starting) if starting else None
            return Hang(rank, Phase.START, round(now - self.launched, 1), self.startup_grace, ranks_seen=len(beats))
        working = {rank: beat for rank, beat in beats.items() if beat.phase not in QUIET_PHASES}
        stopped = self._stopped(working, now)
        if stopped is None and (
            not working or any(now - self.changed[rank][1] <= self.limit(rank, b) for rank, b in working.items())
        ):
            return None
        states = {r: procfs.state(b.pid) for r, b in sorted(beats.items())}
        # the others wait for it in a collective and may have been silent longer: name a stopped rank if any
        silent_longest = min(working, key=lambda rank: self.changed[rank][1])
        named = next((r for r, state in states.items() if state in ("T", "t", "D") and r in working), silent_longest)
        rank = named if stopped is None else stopped
        beat = beats[rank]
        limit = HANG_FLOOR if stopped is not None else self.limit(rank, beat)
        seconds, limit = round(now - self.changed[rank][1], 1), round(limit, 1)
        processes = {str(r): state for r, state in states.items()}
        first = self._first_iteration(rank, beat) or None
        return Hang(rank, beat.phase, seconds, limit, beat.iteration, processes=processes, first=first, hook=beat.hook)

    def _stopped(self, working: dict[int, Heartbeat], now: float) -> int | None:
        """A rank whose process has been stopped (SIGSTOP, a debugger) and silent past the floor, in any phase, the
        first iteration's too (``auto`` only): a stopped process does no slow work."""
        if self.timeout is not None:
            return None
        silent = [rank for rank, beat in working.items() if now - self.changed[rank][1] > HANG_FLOOR]
        return next((rank for rank in silent if procfs.state(working[rank].pid) in ("T", "t")), None)

    def _observe(self, rank: int, beat: Heartbeat, now: float) -> None:
        """A new heartbeat ends the rank's previous phase: time it (past start-up and the first iteration)."""
        previous, since = self.changed.get(rank, (None, now))
        if previous is not None and previous.seq == beat.seq:
            return
        if previous is not None and previous.phase != Phase.START and not self._first_iteration(rank, previous):
            self.longest[previous.phase] = max(self.longest.get(previous.phase, 0.0), now - since)
        if beat.phase != Phase.START:
            self.first.setdefault(rank, beat.iteration)
        for phase, seconds in beat.longest.items():  # the rank's own times: phases too fast for a poll count too
            self.longest[Phase(phase)] = max(self.longest.get(Phase(phase), 0.0), seconds)
        self.changed[rank] = (beat, now)

    def _first_iteration(self, rank: int, beat: Heartbeat) -> bool:
        return beat.phase != Phase.START and beat.iteration == self.first.get(rank)


@dataclass
class Hang:
    """A group silent for longer than its limits, or a start-up that took longer than the grace (``ranks_seen``
    set)."""

    rank: int | None
    phase: Phase
    seconds: float
    limit: float
    iteration: int | None = None
    processes: dict[str, str] | None = None
    """Each rank's process state letter: a stopped (T) or uninterruptible (D) one is named as the hung rank."""
    ranks_seen: int | None = None
    first: bool | None = None
    """True when the rank hung in the first iteration after start-up."""
    hook: str | None = None
    """In phase ``hook``: the hook point and the hook's class (``after_iteration of pkg.mod.Class``)."""

    def fields(self) -> dict:
        """For the event log: the fields that apply (``rank`` always, None if no rank was to blame)."""
        return {key: value for key, value in dataclasses.asdict(self).items() if value is not None or key == "rank"}

    def cause(self) -> str:
        return "killed: start-up hung" if self.ranks_seen is not None else f"killed: rank {self.rank} hung"

    def describe(self) -> str:
        if self.ranks_seen is not None:
            return f"not every rank got past start-up within {self.limit:g} s (--startup-grace)"
        if self.hook:
            where = f"hook {self.hook}" + (", in the first iteration" if self.first else "")
        else:
            where = f"phase {self.phase}" + (" of the first iteration" if self.first else "")
        return f"rank {self.rank} silent for {self.seconds} s in {where} (limit {self.limit} s)"
