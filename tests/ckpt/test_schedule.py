"""When to save: intervals in iterations, seconds or auto (CheckFreq's rule), and the bound on unsaved work."""

from __future__ import annotations

import random

import pytest

from ftrain.ckpt.retention import is_milestone
from ftrain.ckpt.schedule import MAX_AUTO_INTERVAL, MIN_AUTO_INTERVAL, SaveSchedule
from ftrain.config import load_config
from ftrain.errors import UserError
from ftrain.values import Amount, parse_amount

from helpers import SMOKE


def test_amounts_are_iterations_or_durations_and_anything_else_is_one_line_naming_the_key() -> None:
    assert parse_amount("k", 25) == Amount(iterations=25)
    assert parse_amount("k", "90s") == Amount(seconds=90.0)
    assert parse_amount("k", "1.5m") == Amount(seconds=90.0)
    assert parse_amount("k", "2h") == Amount(seconds=7200.0)
    assert parse_amount("k", "auto", auto=True) is None
    for bad in (0, -3, "auto", "10 minutes", "0s", True, 2.5):
        with pytest.raises(UserError, match=r"^k=.* must be a number of iterations \(e\.g\. 100\), a duration"):
            parse_amount("k", bad)
    with pytest.raises(UserError, match=r"checkpoint.interval='soon' must be .* or auto"):
        load_config(SMOKE, ["checkpoint.interval=soon"])
    with pytest.raises(UserError, match=r"checkpoint\.max_unsaved=0 must be"):
        load_config(SMOKE, ["checkpoint.max_unsaved=0"])
    with pytest.raises(UserError, match=r"checkpoint\.max_overhead=1\.5 must be a fraction"):
        load_config(SMOKE, ["checkpoint.max_overhead=1.5"])
    assert load_config(SMOKE, ["checkpoint.interval=auto"]).checkpoint.interval == "auto"


def test_an_iteration_interval_votes_alike_on_every_clock() -> None:
    schedule = SaveSchedule(Amount(iterations=5), 0.02, Amount(iterations=100), now=0.0)
    saved = []
    for step in range(1, 21):
        if schedule.due(step, now=1e9 * step):
            schedule.started(step, now=1e9 * step)
            saved.append(step)
    assert saved == [5, 10, 15, 20]


def test_a_save_left_by_a_busy_writer_comes_at_the_next_free_boundary_and_kept_steps_are_always_due() -> None:
    """Random runs where the writer is busy at random boundaries (a due save then starts nothing): after each multiple
    of the interval a save starts at the first boundary that is not busy, and every pinned step and milestone is due
    (the manager saves those even when busy)."""
    draw = random.Random()
    seed = draw.randrange(2**31)
    draw.seed(seed)
    checked = 0
    for _ in range(200):
        interval, keep_every, steps = draw.randint(1, 6), draw.choice([0, 3, 4, 7]), draw.randint(10, 60)
        pinned = set(draw.sample(range(1, steps + 1), 3))
        busy = {step for step in range(1, steps + 1) if draw.random() < draw.choice([0.2, 0.5, 0.8])}
        kept = lambda step: step in pinned or is_milestone(step, keep_every)  # noqa: B023, E731
        schedule = SaveSchedule(Amount(iterations=interval), 0.02, Amount(iterations=1000), now=0.0, promised=kept)
        saved = set()
        for step in range(1, steps + 1):
            due = schedule.due(step, now=0.0)
            assert due or not kept(step), (seed, step)
            if due and (step not in busy or kept(step)):
                schedule.started(step, now=0.0)
                saved.add(step)
        for multiple in range(interval, steps + 1, interval):
            free = next((step for step in range(multiple, steps + 1) if step not in busy), None)
            assert free is None or any(multiple <= step <= free for step in saved), (seed, interval, multiple)
            checked += 1
        assert {step for step in range(1, steps + 1) if kept(step)} <= saved
    print(f"{checked} due saves over 200 random runs came at the first free boundary (seed {seed})")


def test_a_time_interval_counts_from_the_last_save() -> None:
    schedule = SaveSchedule(Amount(seconds=30.0), 0.02, Amount(iterations=100), now=0.0)
    assert not schedule.due(3, now=29.0)
    assert schedule.due(3, now=30.0)
    schedule.started(3, now=31.0)
    assert not schedule.due(4, now=60.0)
    assert schedule.due(5, now=61.0)


def test_auto_saves_so_that_saving_takes_at_most_the_overhead_bound() -> None:
    schedule = SaveSchedule(None, 0.02, Amount(iterations=100), now=0.0)
    assert schedule.seconds() == MIN_AUTO_INTERVAL  # nothing measured yet: as often as allowed
    schedule.started(10, now=0.0)
    schedule.settled(10, committed=True, cost=0.5)  # 0.5 s of training per save at 2% -> every 25 s
    assert schedule.seconds() == pytest.approx(25.0)
    assert not schedule.due(11, now=24.9) and schedule.due(11, now=25.0)
    schedule.settled(11, committed=True, cost=0.001)
    assert schedule.seconds() == MIN_AUTO_INTERVAL
    schedule.settled(12, committed=True, cost=1e6)
    assert schedule.seconds() == MAX_AUTO_INTERVAL


def test_unsaved_work_counts_from_the_newest_committed_state_not_the_newest_attempt() -> None:
    schedule = SaveSchedule(Amount(iterations=10), 0.02, Amount(seconds=60.0), now=0.0)
    schedule.started(10, now=5.0)
    schedule.settled(10, committed=True, cost=0.1)
    schedule.started(20, now=15.0)
    schedule.settled(20, committed=False, cost=0.1)  # the storage went down
    assert schedule.unsaved(27, now=40.0) == (17, 35.0)
    assert not schedule.over_bound(27, now=65.0)
    assert schedule.over_bound(27, now=65.1)
    by_iterations = SaveSchedule(Amount(iterations=10), 0.02, Amount(iterations=30), now=0.0)
    assert not by_iterations.over_bound(30, now=1e9) and by_iterations.over_bound(31, now=0.0)
