"""The restart policy's crash loop, over generated runs: it stops after exactly ``--crash-loop`` restarts in a row
whose attempts committed nothing new, however late their heartbeats told of the commits that were made."""

from __future__ import annotations

import random
from dataclasses import dataclass

from ftrain.supervise.attempt import Attempt
from ftrain.supervise.options import EXIT_CRASH_LOOP, SupervisorOptions
from ftrain.supervise.outcome import Outcome
from ftrain.supervise.restarts import RestartPolicy

RUNS = 400


@dataclass
class Ended:
    """What the supervisor knows of a failed attempt when it judges it (``supervise.attempt.Attempt``'s fields)."""

    committed: int | None
    progressed: bool = True
    started: bool = False
    started_from: int | None = None


def test_a_crash_loop_stops_after_its_count_of_restarts_that_committed_nothing_new() -> None:
    seed = random.randrange(2**32)
    rng = random.Random(seed)
    for _ in range(RUNS):
        loop = rng.randint(1, 4)
        policy = RestartPolicy(SupervisorOptions(crash_loop=loop, max_restarts=1000))
        newest = rng.choice([None, 4])  # the storage's newest step: the run goes on from an earlier one, or not
        streak = 0  # restarts in a row whose attempt committed nothing, as far as the supervisor can know
        since = 0  # restarts since the newest attempt that committed, told of or not
        unseen = False  # a commit no heartbeat told of: the next attempt that is seen to start shows it
        for index in range(200):
            resumed, unstarted = newest, rng.random() < 0.1  # unstarted: it crashed before it restored any step
            made = not unstarted and rng.random() < 0.3
            newest = (newest or 0) + 4 if made else newest
            regrouped = made and rng.random() < 0.3  # torchrun regrouped its workers after the commit: they resume it
            told = regrouped or (made and rng.random() < 0.5)  # else the save landed as the attempt crashed
            ended = Ended(newest if told else None if unstarted else rng.choice([resumed, None]))
            for start in [] if unstarted else [resumed, newest] if regrouped else [resumed]:
                Attempt.note_start(ended, start)  # as the ledger notes each worker group's start
            if ended.started and unseen:
                streak, unseen = since, False
            streak = 0 if index == 0 or told else streak + 1
            since = 0 if index == 0 or made else since + 1
            judged = policy.judge(ended)
            where = f"seed {seed}, crash loop {loop}, attempt {index}, streak {streak}"
            if streak >= loop:
                assert isinstance(judged, Outcome) and judged.code == EXIT_CRASH_LOOP, where
                assert f"crash loop: {loop} restarts in a row" in judged.message, where
                assert policy.restarts == index, where  # attempts 1..index were its restarts
                break
            assert not isinstance(judged, Outcome), where
            unseen = unseen or (made and not told)
    print(
        f"{RUNS} generated runs of the crash-loop policy, with unseen commits, unseen starts and regroups (seed {seed})"
    )
