"""The restart policy's crash loop, over generated runs: it stops after exactly ``--crash-loop`` restarts in a row
whose attempts committed nothing new, however late their heartbeats told of the commits that were made."""

from __future__ import annotations

import random
from dataclasses import dataclass

from ftrain.supervise.options import EXIT_CRASH_LOOP, SupervisorOptions
from ftrain.supervise.outcome import Outcome
from ftrain.supervise.restarts import RestartPolicy

RUNS = 400


@dataclass
class Ended:
    """What the supervisor knows of a failed attempt when it judges it (``supervise.attempt.Attempt``'s fields)."""

    resumed: int | None
    committed: int | None
    progressed: bool = True


def test_a_crash_loop_stops_after_its_count_of_restarts_that_committed_nothing_new() -> None:
    seed = random.randrange(2**32)
    rng = random.Random(seed)
    for _ in range(RUNS):
        loop = rng.randint(1, 4)
        policy = RestartPolicy(SupervisorOptions(crash_loop=loop, max_restarts=1000))
        newest = rng.choice([None, 4])  # the storage's newest step: the run goes on from an earlier one, or not
        streak = 0  # restarts in a row whose attempt committed nothing (as far as its own heartbeats told)
        for index in range(200):
            resumed, made = newest, rng.random() < 0.3
            newest = (newest or 0) + 4 if made else newest
            told = made and rng.random() < 0.5  # else the save landed as the attempt crashed: its beats missed it
            streak = 0 if index == 0 or told else streak + 1
            judged = policy.judge(Ended(resumed, newest if told else rng.choice([resumed, None])))
            if streak >= loop:
                where = f"seed {seed}, crash loop {loop}, attempt {index}"
                assert isinstance(judged, Outcome) and judged.code == EXIT_CRASH_LOOP, where
                assert f"crash loop: {loop} restarts in a row" in judged.message, where
                assert policy.restarts == index, where  # attempts 1..index were its restarts
                break
            assert not isinstance(judged, Outcome), f"seed {seed}: stopped at attempt {index}, streak {streak}"
            if made and not told:
                streak = 0  # the next attempt resumes from the step it made: the policy learns of it there
    print(f"{RUNS} generated runs of the crash-loop policy (seed {seed})")
