"""The supervisor's accounting across attempts: the step each resumed from, iterations lost and downtime per
recovery (``resumed`` and ``recovered`` events), their totals for the summary, and every change of world size
(``resize`` events: a node lost or joined an elastic run)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from ftrain.errors import counted
from ftrain.heartbeat import Heartbeat, Phase
from ftrain.supervise.attempt import Attempt
from ftrain.supervise.hang import QUIET_PHASES
from ftrain.supervise.outcome import Event, in_words


@dataclass
class Failure:
    """A stop not yet recovered from: when it was detected and how many iterations had completed; ``failed``: a
    failure (else the workers saved on request, as torchrun's agents ask when a node joins)."""

    detected: float
    completed: int
    failed: bool = False


class Ledger:
    def __init__(self, ranks: int, events: Callable[..., None]) -> None:
        self.ranks = ranks
        """Ranks on this node: an attempt has progressed when every one of them completed an iteration."""
        self.events = events
        self.lost = 0
        self.downtime = 0.0
        self.pending: Failure | None = None
        self.committed = 0
        """The newest step committed (0: none): what a failure never recovered from lost up to."""
        self.last: Attempt | None = None
        """The newest attempt observed: a stop that ended it without a save lost what it completed past its commits."""
        self.paused: Failure | None = None
        """When the workers last saved on request and stopped (an elastic regroup, or the end of an attempt)."""
        self.world: int | None = None
        """World size of the last worker group that trained, and the nodes it spanned."""
        self.nodes: list[int] = []
        self.left: set[int] = set()
        """Nodes that left the run on their own (preempted), as opposed to lost."""

    def failed(self, completed: int, now: float) -> None:
        """An attempt failed at ``now`` after ``completed`` iterations (several failures before a recovery are one)."""
        if self.pending is None:
            self.pending = Failure(now, completed, failed=True)
        else:
            self.pending.completed = max(self.pending.completed, completed)

    def observe(self, attempt: Attempt, beats: dict[int, Heartbeat], now: float) -> bool:
        """Track completed iterations and commits; log the resumed step, the first iteration after a failure and
        every change of world size. True when torchrun has restarted this node's workers in a world of another size
        within the attempt (a node joined an elastic run)."""
        if not beats:
            return False
        self.last = attempt
        for beat in beats.values():
            # a checkpoint/done/preempted beat keeps the iteration of the rollout; its committed step may be newer
            attempt.completed = max(attempt.completed, beat.iteration, beat.committed_step or 0)
            if beat.committed_step is not None:
                attempt.committed = max(beat.committed_step, attempt.committed or 0)
                self.committed = max(self.committed, beat.committed_step)
            if beat.resumed_step is not None:  # restored, maybe not yet past its start
                attempt.note_start(beat.resumed_step)
        if self.paused is None and any(beat.phase == Phase.PREEMPTED for beat in beats.values()):
            self.paused = Failure(now, attempt.completed)  # saved on request: torchrun regroups, or the attempt ends
        # a rank that is done or saved on request may be left over from an older world; but where every rank is,
        # the attempt ended before a poll saw it train (a short resumed run), and its beats are all there is to go by
        worlds = {beat.world for beat in beats.values() if beat.phase not in QUIET_PHASES}
        worlds = worlds or {beat.world for beat in beats.values()}
        regrouped = attempt.world is not None and len(worlds) == 1 and worlds != {attempt.world}
        if regrouped:
            attempt.seen = attempt.progressed = False
        if len(worlds) == 1:
            attempt.world = worlds.pop()
        group = {rank: beat for rank, beat in beats.items() if beat.world == attempt.world}
        if not attempt.seen:
            past_start = [beat for beat in group.values() if beat.phase != Phase.START]  # restored by now
            if not past_start:
                return regrouped
            attempt.seen = True
            first = min(past_start, key=lambda beat: beat.rank)
            attempt.resumed = first.resumed_step
            attempt.note_start(attempt.resumed)
            change = {"config_change": first.config_change} if first.config_change else {}
            self.events("resumed", attempt=attempt.plan.attempt, step=attempt.resumed, **change)
        base = attempt.resumed or 0
        if attempt.progressed or len(group) < self.ranks or not all(beat.iteration > base for beat in group.values()):
            return regrouped
        attempt.progressed = True
        stop, self.pending, self.paused = self.pending or self.paused, None, None
        lost = max(0, stop.completed - base) if stop else 0
        downtime = now - stop.detected if stop else 0.0
        if stop is not None and stop.failed:
            self.lost += lost
            self.downtime += downtime
            start = "the start (no checkpoint yet)" if attempt.resumed is None else f"step {attempt.resumed}"
            self.events(
                "recovered",
                f"attempt {attempt.plan.attempt}: recovered from {start} ({counted(lost, 'iteration')} lost, "
                f"{downtime:.1f} s down)",
                attempt=attempt.plan.attempt,
                step=attempt.resumed,
                lost=lost,
                downtime=round(downtime, 3),
            )
        nodes = min(group.values(), key=lambda beat: beat.rank).nodes
        if self.world is not None and self.world != attempt.world:
            self._resized(attempt, nodes, lost, downtime)
        self.world, self.nodes = attempt.world, nodes
        return regrouped

    def seen_commit(self, step: int | None) -> None:
        """``step`` is committed (read from the storage: the workers' last heartbeats may miss a commit made as they
        were stopped)."""
        self.committed = max(self.committed, step or 0)

    def summarize(self, ending: Event, code: int, restarts: int, now: float) -> None:
        """The ``summary`` event that closes the run (``ending``: its event): restarts, iterations lost, downtime. A
        failure no attempt recovered from (the run stopped, or gave up, before one trained again) lost what it had
        completed past the newest commit, and was down until ``now``; so did a last attempt stopped without a save (a
        second signal, or ``--stop-grace`` running out)."""
        if (stop := self.pending) is not None:
            self.lost += max(0, stop.completed - self.committed)
            self.downtime += now - stop.detected
            self.pending = None
        elif (last := self.last) is not None:
            self.lost += max(0, last.completed - max(self.committed, last.resumed or 0))
        lost, downtime = self.lost, self.downtime
        self.events(
            "summary",
            f"{in_words(ending, code)} (exit {code}): {counted(restarts, 'restart')}, "
            f"{counted(lost, 'iteration')} lost, {downtime:.1f} s downtime",
            code=code,
            restarts=restarts,
            iterations_lost=lost,
            downtime=round(downtime, 2),
        )

    def _resized(self, attempt: Attempt, nodes: list[int], lost: int, downtime: float) -> None:
        gone, joined = set(self.nodes) - set(nodes), sorted(set(nodes) - set(self.nodes))
        left, dropped = sorted(gone & self.left), sorted(gone - self.left)
        changes = ((dropped, "lost"), (left, "left (preempted)"), (joined, "joined"))
        why = "; ".join(f"node {', '.join(map(str, group))} {what}" for group, what in changes if group) or (
            "fewer ranks" if attempt.world < self.world else "more ranks"
        )
        self.events(
            "resize",
            f"attempt {attempt.plan.attempt}: world {self.world} -> {attempt.world} ranks ({why}), resumed from step "
            f"{attempt.resumed}: {downtime:.1f} s down, {counted(lost, 'iteration')} lost",
            attempt=attempt.plan.attempt,
            old_world=self.world,
            new_world=attempt.world,
            old_nodes=self.nodes,
            new_nodes=nodes,
            why=why,
            step=attempt.resumed,
            lost=lost,
            downtime=round(downtime, 3),
        )
