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


def test_iterations_lost_are_counted_whether_or_not_a_recovery_follows(tmp_path) -> None:
    """Generated schedules (seeded): attempts of one rank train, commit every 2nd iteration, and fail; a restart may
    fail again before it trains, and the run may end (a preemption, a crash loop) before any attempt recovers, or
    with a stop of the last attempt that did not save (a second signal). The summary's iterations lost is a simple
    model's: per failure, what was completed past the step the next training attempt resumed from, or past the newest
    commit where none did; and what the last attempt completed past the newest commit when it was stopped."""
    import random

    from ftrain.supervise.attempt import Attempt

    checked = unrecovered = recoveries = unsaved = 0
    for case in range(60):
        draw, logged = random.Random(case), []
        ledger = Ledger(1, lambda name, message="", _into=logged, **fields: _into.append((name, fields)))
        completed = committed = expected = 0
        failure: int | None = None  # iterations completed when the pending failure happened
        attempt_number, now = 0, 0.0
        for _ in range(draw.randint(1, 6)):
            attempt = Attempt(Plan(generation=1, attempt=attempt_number, port=None), ["true"], {}, "token", tmp_path)
            attempt.proc.wait()
            attempt_number += 1
            base = committed
            completed = base
            beat = Heartbeat(0, 1, base, Phase.START, committed or None, base or None, 0, now)
            ledger.observe(attempt, {0: beat}, now)
            for _ in range(draw.choice([0, 0, 1, 3, 5])):  # 0: fails (or is stopped) again before it trains
                completed += 1
                committed = completed if completed % 2 == 0 else committed
                now += 1.0
                beat = Heartbeat(0, 1, completed, Phase.ROLLOUT, committed or None, base or None, completed, now)
                ledger.observe(attempt, {0: beat}, now)
                if failure is not None:  # the first iteration past the resumed step: recovered
                    expected, failure = expected + max(0, failure - base), None
            if draw.random() < 0.7:
                ledger.failed(attempt.completed, now)
                failure = max(failure or 0, completed)
        now += 1.0
        ledger.summarize("preempted", 143, attempt_number - 1, now)
        if failure is not None:
            expected += max(0, failure - committed)
            unrecovered += 1
        else:  # stopped: a save would have committed ``completed``; an odd one was not saved
            expected += completed - committed
            unsaved += completed > committed
        (summary,) = [fields for name, fields in logged if name == "summary"]
        assert summary["iterations_lost"] == expected, (case, logged)
        checked += 1
        recoveries += sum(name == "recovered" for name, _ in logged)
    print(
        f"{checked} schedules: iterations lost as the model counts them ({recoveries} recoveries; {unrecovered} "
        f"runs ended before a recovery; {unsaved} stopped without a save)"
    )
    assert unrecovered >= 10 and recoveries >= 10 and unsaved >= 5
