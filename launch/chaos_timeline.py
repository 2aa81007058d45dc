"""Where a chaos run's time went, from what ``ftrain supervise`` and its workers record: torchrun launches (the
``start`` events of ``events.jsonl``) and every heartbeat write seen while polling (each carries the time it was
written). Used by ``bench_chaos.py`` (which imports ``bench_recovery`` first: that puts this repository on
``sys.path``)."""

from __future__ import annotations

import itertools
import math
import statistics
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from ftrain.heartbeat import Heartbeat, read_heartbeats


class Timeline:
    """Every heartbeat write seen in a log directory, by (pid, seq)."""

    def __init__(self, heartbeat_dir: Path) -> None:
        self.dir = heartbeat_dir
        self.beats: dict[tuple[int, int], Heartbeat] = {}

    def poll(self) -> dict[int, Heartbeat]:
        beats = read_heartbeats(self.dir)
        for beat in beats.values():
            self.beats.setdefault((beat.pid, beat.seq), beat)
        return beats

    def by_pid(self) -> dict[int, list[Heartbeat]]:
        found: dict[int, list[Heartbeat]] = defaultdict(list)
        for (pid, _), beat in sorted(self.beats.items(), key=lambda item: item[1].time):
            found[pid].append(beat)
        return found

    def save_seconds(self) -> float:
        """Rank 0's time in the checkpoint phase (a checkpoint beat until its process's next beat, where seen)."""
        total = 0.0
        for beats in self.by_pid().values():
            for beat, after in itertools.pairwise(beats):
                if beat.rank == 0 and beat.phase == "checkpoint" and after.seq == beat.seq + 1:
                    total += after.time - beat.time
        return total

    def median_iteration(self) -> float:
        """The median time between consecutive rollout beats of one rank-0 process (a steady iteration)."""
        gaps = []
        for beats in self.by_pid().values():
            rollouts = [b for b in beats if b.rank == 0 and b.phase == "rollout"]
            gaps += [b.time - a.time for a, b in itertools.pairwise(rollouts) if b.iteration == a.iteration + 1]
        return statistics.median(gaps) if gaps else math.nan

    def iteration_seconds(self) -> float:
        """Wall time per iteration of rank 0's first process, evaluation and saves included (the straight run)."""
        beats = next(beats for beats in self.by_pid().values() if beats[0].rank == 0)
        first = next(b for b in beats if b.phase == "rollout")
        last = max(beats, key=lambda b: (b.iteration, -b.time))
        return (last.time - first.time) / max(1, last.iteration - first.iteration)


@dataclass
class Attempt:
    """One torchrun launch of the chaos run, as its workers' heartbeats tell it."""

    launched: float
    ready: float | None = None
    """Every rank's first ``start`` beat: imports, rendezvous, environments and model built."""
    restored: float | None = None
    """Every rank past its ``start`` beats (the checkpoint restored, the first rollout begun)."""
    first: float | None = None
    """Every rank past the step it resumed from: the first iteration done."""
    resumed: int = 0
    top: int = 0


def attempts(timeline: Timeline, launches: list[float]) -> list[Attempt]:
    """Each torchrun launch with the phases of the workers it started (a worker belongs to the last launch before
    its first beat)."""
    found = [Attempt(t) for t in launches]
    workers: dict[int, list[list[Heartbeat]]] = defaultdict(list)
    for beats in timeline.by_pid().values():
        index = max((i for i, t in enumerate(launches) if t <= beats[0].time), default=None)
        if index is not None:
            workers[index].append(beats)
    for index, processes in workers.items():
        attempt = found[index]
        starts = [[b for b in beats if b.phase == "start"] for beats in processes]
        attempt.resumed = max((b.resumed_step or 0 for beats in processes for b in beats), default=0)
        attempt.top = max(b.iteration for beats in processes for b in beats)
        if all(s and s[0].seq == 1 for s in starts):
            attempt.ready = max(s[0].time for s in starts)
        trains = [next((b.time for b in beats if b.phase != "start"), None) for beats in processes]
        if None not in trains:  # the second start beat (restored) lasts a moment: the first rollout follows at once
            attempt.restored = max(trains)
        past = [next((b.time for b in beats if b.iteration > attempt.resumed), None) for beats in processes]
        if len(processes) >= 2 and None not in past:
            attempt.first = max(past)
    return found


def lost_iterations(found: list[Attempt]) -> list[int]:
    """Per attempt after the first, the iterations done before that it does again (as the supervisor's ledger
    counts them, across supervisor processes too)."""
    frontier, lost = found[0].top, []
    for attempt in found[1:]:
        lost.append(max(0, frontier - attempt.resumed) if attempt.top > attempt.resumed else 0)
        frontier = attempt.top if attempt.top > attempt.resumed else max(frontier, attempt.top)
    return lost


def stopped(timeline: Timeline, attempt: Attempt, until: float) -> float:
    """When an attempt stopped being useful: the last iteration completed (on any rank) before ``until``, or
    its own start-up, if later (a restart that failed in start-up: that time is start-up, not detection)."""
    progress = [b.time for b in timeline.beats.values() if b.phase == "rollout" and attempt.launched <= b.time < until]
    steps = [t for t in (attempt.ready, attempt.restored, attempt.first) if t and t < until]
    return max([attempt.launched, *progress, *steps])
