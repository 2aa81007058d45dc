"""How an attempt ended, from what the supervisor saw: finished, preempted, bad input, or failed (restart)."""

from __future__ import annotations

import enum
import math
import signal
from dataclasses import dataclass

from ftrain.errors import (
    CONTINUE,
    EXIT_RENDEZVOUS_TIMEOUT,
    EXIT_STORAGE_DOWN,
    EXIT_STORAGE_HELD,
    EXIT_USAGE,
    STOPPED,
)
from ftrain.heartbeat import Phase
from ftrain.supervise.options import EXIT_DONE, EXIT_INTERRUPTED, EXIT_TOO_FEW_NODES


class Event(enum.StrEnum):
    """How an attempt ended, by the name the events log gives it: a restart (``FAILED``), a wait for the storage
    (``STORAGE_DOWN``), another node gone with this one's workers saved (``REGROUP``), or an ending of the run."""

    DONE = "done"
    PREEMPTED = "preempted"
    FAILED = "failed"
    STORAGE_DOWN = "storage_down"
    STORAGE_HELD = "storage_held"
    USAGE = "usage"
    PEER_ENDED = "peer_ended"
    PEER_LOST = "peer_lost"
    REGROUP = "regroup"
    MAX_RESTARTS = "max_restarts"
    CRASH_LOOP = "crash_loop"
    NOT_ADMITTED = "not_admitted"
    TOO_FEW_NODES = "too_few_nodes"


@dataclass
class WorkerFailure:
    """How one worker ended, as torchrun saw it."""

    code: int
    """Its exit code; negative: killed by that signal."""
    error: str | None
    """The one-line error it recorded in its error file, if any."""
    recorded_at: float = math.inf
    """When it recorded that error (epoch seconds; infinity: not known)."""


def blame(failures: dict[int, WorkerFailure], killed: set[int]) -> tuple[int, WorkerFailure] | None:
    """The rank to blame for ``failures`` (global rank -> how it ended) and how it ended.

    Ranks the supervisor ``killed`` do not count. Of the others, a rank that refused its input comes first (the
    lowest: every rank refuses alike, and the others may have been stopped by torchrun before they could exit 2), then
    one that found the storage taken by another run (exit 8), then one that could not reach the storage (exit 7), then
    a rank killed by a signal (someone killed it; the rest then failed on the broken group), then the rank that
    recorded an error first (the others' errors, a broken connection, followed it), then a specific exit code before 1
    (what a broken group gives) or SIGTERM (what torchrun sends the survivors), then the lowest rank. torchrun's own
    root cause is only the first failure it noticed, arbitrary when several die within a poll.
    """
    own = {rank: failure for rank, failure in failures.items() if rank not in killed} or failures

    def order(item: tuple[int, WorkerFailure]) -> tuple:
        rank, failure = item
        if failure.code in FINAL_FIRST:
            return (False, FINAL_FIRST.index(failure.code), rank)
        signalled = failure.code < 0 and failure.code != -signal.SIGTERM
        return (True, not signalled, failure.recorded_at, failure.code in (1, -signal.SIGTERM), rank)

    return min(own.items(), key=order) if own else None


FINAL_FIRST = (EXIT_USAGE, EXIT_STORAGE_HELD, EXIT_STORAGE_DOWN)
"""Exit codes that name their cause (bad input, the storage lost to another run, the storage down), in the order
they are blamed before any other."""
ENDINGS = {Event.USAGE: "bad input", Event.DONE: "training finished"}
"""How the summary names an ending whose event name is not plain words."""


def newest_step(step: int | None) -> str:
    """The newest committed step, in words: "newest step 40", or "no step committed yet"."""
    return f"newest step {step}" if step is not None else "no step committed yet"


def stopped_by(code: int, how: str, committed: int | None) -> Outcome:
    """A run stopped by a signal (``code``: 130 for SIGINT, "interrupted", else "preempted"), ``how`` its workers
    ended, and the step the same command goes on from."""
    event = Event.PREEMPTED
    return Outcome(event, code, f"{in_words(event, code)}: {how} ({newest_step(committed)}); {CONTINUE}")


def finished(step: int | None, how: str = "") -> Outcome:
    """Training finished at ``step`` (``how``: seen how, if not from this node's own workers)."""
    return Outcome(Event.DONE, EXIT_DONE, f"training finished (step {step}{'; ' + how if how else ''})")


def peer_ended(code: int) -> Outcome:
    """The run ended on another node, with exit ``code``."""
    return Outcome(Event.PEER_ENDED, code, f"another node ended the run with exit code {code}")


def not_admitted(committed: int | None) -> Outcome:
    """An elastic node that neither keeps the plan nor hosts the rendezvous joined no worker group within
    --rdzv-timeout: fewer than MIN nodes met, or (it came back late) the nodes training did not take it in. It ends
    alone: the others time out by themselves in the first case, and train on in the second."""
    newest = f"newest step {committed}" if committed is not None else "this node saw no commit"
    return Outcome(
        Event.NOT_ADMITTED,
        EXIT_TOO_FEW_NODES,
        f"this node joined no worker group within --rdzv-timeout: fewer than MIN nodes met, or the nodes training did "
        f"not take it in; the other nodes are not stopped and nothing committed is lost ({newest}): start the missing "
        f"nodes, or run the same command again on this node to rejoin",
    )


def in_words(event: Event, code: int | None = None) -> str:
    """The name of an ending (an event, with its exit ``code``) for a person: ``usage`` is "bad input",
    ``crash_loop`` "crash loop", a preemption by SIGINT (exit 130) "interrupted", as the exit codes' help says."""
    if event == Event.PREEMPTED and code == EXIT_INTERRUPTED:
        return "interrupted"
    return ENDINGS.get(event, event.replace("_", " "))


@dataclass
class Outcome:
    """How an attempt ended: ``failed`` (restart), ``storage_down`` (wait for the storage, then restart) or one of the
    endings, with its exit code and event name."""

    event: Event
    code: int | None
    message: str

    @property
    def failed(self) -> bool:
        return self.event in (Event.FAILED, Event.STORAGE_DOWN)


def classify(
    code: int,
    cause: str,
    culprit: tuple[int, WorkerFailure] | None,
    stopped: int | None,
    orphans: bool,
    phases: set[str],
    superseded: bool,
    committed: int | None,
) -> Outcome:
    """The outcome of an attempt whose torchrun exited with ``code`` (``ftrain.torchrun``: 130 or 143 when every
    worker that ended exited so, after a stop by SIGINT or SIGTERM that reached the workers but not the supervisor).

    ``cause``: what to blame, in words; ``culprit``: the rank to blame and how it ended, if any;
    ``stopped``: the exit code for the signal that asked the supervisor to stop (None: no signal); ``orphans``:
    workers outlived torchrun; ``phases``: the final heartbeat phases; ``superseded``: several nodes, and another node
    ended this attempt: it failed it, or (elastic, the run going on) its torchrun stopped every rank's workers for a
    node that joined late (the first agent to see the new node stops its workers, and through the iteration boundary
    they agree on, everyone's, before the other agents have looked); ``committed``: the newest step committed.
    """
    if phases == {Phase.DONE} and not orphans:  # every worker committed the last step: whatever torchrun said after
        return finished(committed, "the stop came after the last step" if stopped is not None else "")
    if stopped is not None:
        saved = bool(phases) and phases <= {Phase.PREEMPTED, Phase.DONE}
        how = "the workers saved" if saved else "the workers did not all confirm a save"
        how = how if phases else "the workers stopped before training began"  # not one heartbeat: nothing to save
        return stopped_by(stopped, how, committed)
    if orphans:
        return Outcome(Event.FAILED, None, cause)
    if code == 0:
        return finished(committed)
    if (
        code in STOPPED and phases and phases <= {Phase.PREEMPTED, Phase.DONE}
    ):  # the workers were signalled, saved, exited
        if superseded:
            return Outcome(
                Event.FAILED, None, "stopped by another node (it failed, or restarted for a node that joined)"
            )
        return stopped_by(code, "the workers saved", committed)
    if code == EXIT_RENDEZVOUS_TIMEOUT and culprit is None:
        return Outcome(
            Event.TOO_FEW_NODES,
            EXIT_TOO_FEW_NODES,
            f"fewer nodes than the minimum joined within --rdzv-timeout; nothing committed is lost "
            f"({newest_step(committed)}): start the missing nodes and run the same command again",
        )
    if culprit is not None and culprit[1].code == EXIT_STORAGE_DOWN:
        return Outcome(
            Event.STORAGE_DOWN, None, f"rank {culprit[0]}: {culprit[1].error or 'the storage did not answer'}"
        )
    if culprit is not None and culprit[1].code == EXIT_USAGE:
        rank, failure = culprit
        refusal = f"refused its input: {failure.error}" if failure.error else f"exited with code {EXIT_USAGE}"
        return Outcome(Event.USAGE, EXIT_USAGE, f"rank {rank} {refusal}; not restarting")
    if culprit is not None and culprit[1].code == EXIT_STORAGE_HELD:  # another run took the storage: a restart would
        rank, failure = culprit  # be refused too
        held = failure.error or "another run holds the storage"
        return Outcome(Event.STORAGE_HELD, EXIT_STORAGE_HELD, f"rank {rank}: {held}; not restarting")
    return Outcome(Event.FAILED, None, cause)
