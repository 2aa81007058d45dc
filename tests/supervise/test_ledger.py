"""The supervisor's ledger on heartbeats as its polls find them."""

from __future__ import annotations

from ftrain.heartbeat import Heartbeat, Phase
from ftrain.supervise.attempt import Attempt
from ftrain.supervise.ledger import Ledger
from ftrain.supervise.plan import Plan

CHANGE = "algorithm.gamma 0.99 -> 0.98"


def test_a_resumed_attempt_that_ended_between_two_polls_is_still_logged(tmp_path) -> None:
    """A short resumed run can finish between two polls, so that the first heartbeats the supervisor reads are the
    final ones (done): the step it resumed from and what changed there must still reach the events."""
    logged = []
    ledger = Ledger(2, lambda name, message="", **fields: logged.append((name, fields)))
    attempt = Attempt(Plan(generation=1, attempt=0, port=None), ["true"], {}, "token", tmp_path)
    attempt.proc.wait()
    done = {rank: Heartbeat(rank, 1, 4, Phase.DONE, 4, 2, 9, 0.0, world=2, config_change=CHANGE) for rank in (0, 1)}
    ledger.observe(attempt, done, now=1.0)
    assert ("resumed", {"attempt": 0, "step": 2, "config_change": CHANGE}) in logged
    assert attempt.resumed == 2 and attempt.committed == 4 and ledger.world == 2


def test_ranks_done_in_an_older_world_do_not_stand_for_the_training_one(tmp_path) -> None:
    """Beside a rank that trains, a done rank of another world size is a leftover: the world is the training one's."""
    ledger = Ledger(2, lambda *args, **fields: None)
    attempt = Attempt(Plan(generation=1, attempt=1, port=None), ["true"], {}, "token", tmp_path)
    attempt.proc.wait()
    beats = {
        0: Heartbeat(0, 1, 6, Phase.ROLLOUT, 4, 4, 9, 0.0, world=1),
        1: Heartbeat(1, 2, 4, Phase.DONE, 4, None, 9, 0.0, world=2),
    }
    ledger.observe(attempt, beats, now=1.0)
    assert attempt.world == 1
