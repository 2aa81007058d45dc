"""Hangs told from slow work, both ways: each phase has its own limit, learnt from its own times; start-up and the
first iteration after it get the start-up grace. In-process against made-up heartbeats, then a real supervised run
whose first iteration takes twice the floor (not a hang) and whose worker, stopped later, is caught within seconds."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
import types
import uuid

import pytest

from ftrain import procfs
from ftrain.heartbeat import Heartbeat, HeartbeatWriter, Phase, read_heartbeats, read_stop_reason, write_stop_reason
from ftrain.supervise.attempt import Attempt, attempt_env
from ftrain.supervise.hang import HANG_FACTOR, HANG_FLOOR, HangWatch
from ftrain.supervise.plan import Plan
from ftrain.train.hooks import Hook, Hooks

from helpers import (
    REPO,
    SMOKE,
    TESTS,
    child_env,
    events,
    finish,
    hooks_override,
    launch,
    probe_hook,
    training,
    wait_for,
)

GRACE = 60.0
FIRST = 2 * HANG_FLOOR
"""Seconds the real run's first iteration takes: past the floor, so only the start-up grace lets it pass."""


def beat(rank: int, seq: int, phase: Phase, iteration: int, longest: dict | None = None) -> Heartbeat:
    return Heartbeat(rank, os.getpid(), iteration, phase, None, None, seq, 0.0, longest=longest or {})


def both(watch: HangWatch, seq: int, phase: Phase, iteration: int, now: float):
    """Both ranks' heartbeats at ``now``; the hang ``watch`` sees, if any."""
    return watch.check({0: beat(0, seq, phase, iteration), 1: beat(1, seq, phase, iteration)}, now)


def steady(watch: HangWatch, now: float, iterations: range, rollout: float = 0.2, update: float = 0.1) -> float:
    """Iterations with these phase times from ``now``; returns the time after them."""
    for iteration in iterations:
        assert both(watch, 10 + 2 * iteration, Phase.ROLLOUT, iteration, now) is None
        now += rollout
        assert both(watch, 11 + 2 * iteration, Phase.UPDATE, iteration, now) is None
        now += update
    return now


def test_start_up_has_the_grace_and_is_named_as_such():
    watch = HangWatch(timeout=None, startup_grace=10, ranks=2)
    watch.restart(now=0)
    assert watch.check({0: beat(0, 1, Phase.START, 0)}, now=9) is None
    late = watch.check({0: beat(0, 1, Phase.START, 0)}, now=11)
    assert (late.phase, late.limit, late.ranks_seen) == ("start", 10, 1)
    assert late.cause() == "killed: start-up hung" and "iteration" not in late.fields()


def test_a_stop_is_caught_in_a_phase_too_fast_for_any_poll_to_have_seen():
    """Updates and saves of a few milliseconds between polls a tenth of a second apart: the watch never saw one, and
    rank 0 then waits in an update for a stopped rank 1. The ranks' own times in their heartbeats give the floor."""
    watch = HangWatch(timeout=None, startup_grace=GRACE, ranks=2)
    watch.restart(now=0)
    assert both(watch, 1, Phase.START, 0, now=0) is None
    timed = {"rollout": 0.08, "update": 0.004, "checkpoint": 0.002}
    for iteration in range(6):  # each poll happens to see a rollout
        beats = {rank: beat(rank, 2 + iteration, Phase.ROLLOUT, iteration, timed) for rank in (0, 1)}
        assert watch.check(beats, now=1 + iteration / 10) is None
    assert watch.longest[Phase.UPDATE] == 0.004
    stuck = {0: beat(0, 20, Phase.CHECKPOINT, 6, timed), 1: beat(1, 20, Phase.ROLLOUT, 6, timed)}
    assert watch.check(stuck, now=1.6) is None
    hang = watch.check(stuck, now=1.6 + HANG_FLOOR + 0.1)
    assert hang is not None and hang.limit == HANG_FLOOR


def test_a_stopped_process_is_hung_after_the_floor_even_in_its_first_iteration():
    """A rank stopped (SIGSTOP) right after a restart, in the first iteration that has the start-up grace: a stopped
    process does no slow work, so the floor applies (a real stopped child process)."""
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        os.kill(child.pid, signal.SIGSTOP)
        wait_for(lambda: procfs.state(child.pid) == "T", "the child stopped")
        watch = HangWatch(timeout=None, startup_grace=GRACE, ranks=2)
        watch.restart(now=0)
        stopped = Heartbeat(1, child.pid, 0, Phase.ROLLOUT, None, None, 2, 0.0)
        beats = {0: beat(0, 2, Phase.UPDATE, 0), 1: stopped}
        assert watch.check({0: beat(0, 1, Phase.START, 0), 1: beat(1, 1, Phase.START, 0)}, now=0) is None
        assert watch.check(beats, now=1) is None
        assert watch.check(beats, now=1 + HANG_FLOOR) is None
        hang = watch.check(beats, now=1.2 + HANG_FLOOR)
        assert (hang.rank, hang.limit, hang.first, hang.processes["1"]) == (1, HANG_FLOOR, True, "T")
    finally:
        child.kill()
        child.wait()


def test_a_hook_of_the_config_runs_in_a_phase_that_names_it_with_its_iteration_counted_as_completed(tmp_path):
    """What the hook sees in its own heartbeat while it runs, then after: in ``after_iteration`` the iteration is
    complete (a hook that fails there loses it, and the supervisor counts it lost), and the phase it interrupted goes
    on; ours, and the points it does not implement, beat nothing."""
    seen = []

    class Builtin(Hook):
        def after_iteration(self, trainer, metrics) -> None:
            seen.append(("builtin", read_heartbeats(tmp_path)[0]))

    class Users(Hook):
        def after_iteration(self, trainer, metrics) -> None:
            seen.append(("user", read_heartbeats(tmp_path)[0]))

    writer = HeartbeatWriter(tmp_path, rank=0)
    trainer = types.SimpleNamespace(heartbeat=writer, iteration=4)
    hooks = Hooks([Builtin()], [Users()])
    writer.beat(Phase.UPDATE, 3)
    hooks.call("after_update", trainer, {})  # implemented by neither
    assert writer.seq == 1
    hooks.call("after_iteration", trainer, {})
    (_, builtin), (_, user) = seen
    assert (builtin.phase, builtin.hook, builtin.seq) == (Phase.UPDATE, None, 1)
    name = f"after_iteration of {__name__}.{Users.__qualname__}"
    assert (user.phase, user.hook, user.iteration) == (Phase.HOOK, name, 4)  # completed: lost if it fails
    after = read_heartbeats(tmp_path)[0]
    assert (after.phase, after.hook, after.seq, after.iteration) == (Phase.UPDATE, None, 3, 4)
    hang = HangWatch(timeout=None, startup_grace=GRACE, ranks=1)
    hang.restart(now=0)
    assert hang.check({0: beat(0, 1, Phase.ROLLOUT, 4)}, now=0) is None  # the first iteration of an attempt
    described = hang.check({0: user}, now=1), hang.check({0: user}, now=2 + GRACE)
    assert (
        described[0] is None and f"in hook {name}, in the first iteration (limit {GRACE} s)" in described[1].describe()
    )


def test_a_slow_first_iteration_is_not_a_hang_and_a_stop_in_a_fast_phase_is_caught_in_seconds():
    watch = HangWatch(timeout=None, startup_grace=GRACE, ranks=2)
    watch.restart(now=0)
    assert both(watch, 1, Phase.START, 0, now=0) is None
    assert both(watch, 2, Phase.ROLLOUT, 0, now=3) is None  # start-up over: the first iteration begins
    assert both(watch, 2, Phase.ROLLOUT, 0, now=48) is None  # 45 s into the first rollout: the grace applies
    now = steady(watch, 50, range(1, 6))
    assert watch.longest == pytest.approx({Phase.ROLLOUT: 0.2, Phase.UPDATE: 0.1})  # not the first iteration's 45 s
    # rank 1 stops in a rollout; rank 0 goes on to the update and waits there in a collective
    assert both(watch, 30, Phase.ROLLOUT, 6, now) is None
    stuck = {0: beat(0, 31, Phase.UPDATE, 6), 1: beat(1, 30, Phase.ROLLOUT, 6)}
    assert watch.check(stuck, now + 0.2) is None
    assert watch.check(stuck, now + HANG_FLOOR + 0.1) is None  # rank 0 has waited less than its limit
    hung = watch.check(stuck, now + HANG_FLOOR + 0.3)
    assert (hung.rank, hung.phase, hung.limit, hung.iteration) == (1, "rollout", HANG_FLOOR, 6)
    assert hung.describe() == f"rank 1 silent for {HANG_FLOOR + 0.3} s in phase rollout (limit {HANG_FLOOR} s)"

    # the next attempt: its first iteration has the grace again, its later ones the limits learnt before
    watch.restart(now=1000)
    assert both(watch, 1, Phase.START, 6, now=1000) is None
    assert both(watch, 2, Phase.ROLLOUT, 6, now=1004) is None
    assert both(watch, 2, Phase.ROLLOUT, 6, now=1004 + GRACE - 1) is None
    hung = both(watch, 2, Phase.ROLLOUT, 6, now=1004 + GRACE + 1)
    assert (hung.first, hung.limit) == (True, GRACE) and "of the first iteration" in hung.describe()


def test_each_phase_has_its_own_limit_and_an_unseen_one_the_grace():
    watch = HangWatch(timeout=None, startup_grace=GRACE, ranks=2)
    watch.restart(now=0)
    both(watch, 1, Phase.START, 0, now=0)
    now = steady(watch, 1, range(0, 4))
    assert both(watch, 20, Phase.EVALUATE, 4, now) is None
    assert both(watch, 20, Phase.EVALUATE, 4, now + GRACE - 1) is None  # the first evaluation: no limit learnt yet
    assert both(watch, 21, Phase.ROLLOUT, 4, now + 20) is None  # it took 20 s: 200 s for the next one
    now = steady(watch, now + 20, range(4, 8), rollout=0.6)
    assert watch.longest[Phase.EVALUATE] == pytest.approx(20) and watch.longest[Phase.ROLLOUT] == pytest.approx(0.6)
    assert both(watch, 40, Phase.EVALUATE, 8, now) is None
    assert both(watch, 40, Phase.EVALUATE, 8, now + HANG_FACTOR * 20 - 1) is None
    assert both(watch, 40, Phase.EVALUATE, 8, now + HANG_FACTOR * 20 + 1).limit == HANG_FACTOR * 20


def test_rank_0_closing_slowly_beside_a_peer_that_closed_at_once_has_the_grace():
    """The end of an attempt: rank 1 closes in 0.01 s and says so in its heartbeat; rank 0 flushes its trackers for
    40 s. A close is once per attempt and rank 0's alone does that work: no peer's close limits it."""
    watch = HangWatch(timeout=None, startup_grace=GRACE, ranks=2)
    watch.restart(now=0)
    both(watch, 1, Phase.START, 0, now=0)
    now = steady(watch, 1, range(0, 4))
    closing = {0: beat(0, 30, Phase.CLOSING, 4), 1: beat(1, 31, Phase.DONE, 4, {"closing": 0.01})}
    assert watch.check(closing, now) is None
    assert watch.longest[Phase.CLOSING] == 0.01
    assert watch.check(closing, now + 40) is None
    assert watch.check(closing, now + GRACE + 1).limit == GRACE


def test_a_rank_that_beats_keeps_the_group_alive():
    """Rank 0 holds a save (beating every 0.5 s) while rank 1 waits for it in a collective, silent: slow work."""
    watch = HangWatch(timeout=None, startup_grace=GRACE, ranks=2)
    watch.restart(now=0)
    both(watch, 1, Phase.START, 0, now=0)
    now = steady(watch, 1, range(0, 4))
    for seq, at in enumerate(range(int(now) + 1, int(now) + 60), start=50):
        assert watch.check({0: beat(0, seq, Phase.CHECKPOINT, 4), 1: beat(1, 17, Phase.ROLLOUT, 4)}, at) is None


def test_a_fixed_timeout_holds_for_every_phase_after_start_up():
    watch = HangWatch(timeout=2, startup_grace=GRACE, ranks=2)
    watch.restart(now=0)
    both(watch, 1, Phase.START, 0, now=0)
    assert both(watch, 2, Phase.ROLLOUT, 0, now=1) is None
    assert both(watch, 2, Phase.ROLLOUT, 0, now=3.1).limit == 2  # even in the first iteration
    assert both(watch, 3, Phase.DONE, 1, now=100) is None  # ranks that finished only exit


@pytest.mark.slow
@pytest.mark.waits  # a slow first iteration, a stopped worker and a slow end: under 30% of it on the CPU
def test_a_slow_first_iteration_is_not_a_hang_and_a_stopped_worker_is_caught_in_seconds(tmp_path):
    """In one real supervised run: the first iteration of a fresh start sleeps ``FIRST`` s (both ranks), twice the
    floor any later phase gets; later a worker is stopped in the middle of 0.05 s phases and is called hung at the
    floor (asserted within the floor + ``FIRST``: a margin for a machine 3x slower); the run's end (its last save,
    the hooks' ``on_end``: trackers flushing) takes ``FIRST`` s too, after saves of a fraction of a second, and is
    no hang either. After the restart, a hook of the config hangs rank 0: the hang names the hook."""
    run = tmp_path / "run"
    command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "2", "--backoff-initial", "0.2"]
    command += [SMOKE, "--storage", str(run), "iterations=60", "log.console=false"]
    hooks = [probe_hook(hook, seconds=FIRST) for hook in ("SlowFirstIterationHook", "SlowEndHook")]
    command += [hooks_override(*hooks, probe_hook("HangOnceHook", iteration=30, marker=tmp_path / "hung"))]
    output = (tmp_path / "supervise.log").open("wb")
    env = child_env({"PYTHONPATH": str(TESTS)})
    supervisor = launch(command, cwd=REPO, env=env, stdout=output, stderr=subprocess.STDOUT)
    victim = training(run / "heartbeat", 8)[1]
    assert not [event for event in events(run) if event["event"] == "hang"]  # the slow first iteration passed
    stopped = time.time()
    os.kill(victim.pid, signal.SIGSTOP)
    hang = wait_for(lambda: next((e for e in events(run) if e["event"] == "hang"), None), "a hang", 60, 0.05)
    detected = hang["time"] - stopped
    print(f"the stopped worker was called hung {detected:.2f} s after its SIGSTOP (limit {hang['limit']} s)")
    assert hang["rank"] == 1 and hang["processes"]["1"] == "T" and hang["limit"] == HANG_FLOOR
    assert detected < HANG_FLOOR + FIRST
    assert finish(supervisor, timeout=180) == 0, (tmp_path / "supervise.log").read_text()[-3000:]
    with (run / "metrics.csv").open() as file:
        assert float(next(csv.DictReader(file))["collect_time"]) >= FIRST  # the first iteration was that slow
    exits = [e["cause"] for e in events(run) if e["event"] == "exit"]
    assert exits[:2] == ["killed: rank 1 hung", "killed: rank 0 hung"]
    hangs = [e for e in events(run) if e["event"] == "hang"]
    hook = "after_iteration of probe_hooks.HangOnceHook"
    assert len(hangs) == 2 and (hangs[1]["phase"], hangs[1]["hook"], hangs[1]["iteration"]) == ("hook", hook, 30)
    assert hangs[1]["rank"] == 0 and hangs[1]["limit"] == HANG_FLOOR
    assert f"in hook {hook} (limit {HANG_FLOOR} s)" in (tmp_path / "supervise.log").read_text()
    recovered = [event for event in events(run) if event["event"] == "recovered"]
    assert len(recovered) == 2 and all(event["downtime"] >= HANG_FLOOR for event in recovered), recovered  # silent too


def test_the_reason_for_a_stop_is_read_by_the_workers_and_gone_at_the_next_attempt(tmp_path) -> None:
    """The supervisor stops workers with SIGTERM whatever it got, and says in the heartbeat directory what that was."""
    beats = tmp_path / "heartbeat"
    attempt_env(beats, "token", 1.0, 0, {})
    assert read_stop_reason(beats) is None and read_stop_reason(None) is None
    write_stop_reason(beats, signal.SIGINT)
    assert read_stop_reason(beats) == "SIGINT to the supervisor (Ctrl-C), passed on as SIGTERM"
    write_stop_reason(beats, signal.SIGTERM)
    assert read_stop_reason(beats) == "SIGTERM to the supervisor"
    (beats / "rank-0.json").write_text("{}")
    attempt_env(beats, "token", 1.0, 0, {})  # the next attempt's workers were not stopped
    assert read_stop_reason(beats) is None and not list(beats.iterdir())


def test_an_ended_attempt_is_killed_to_the_last_process_its_warm_workers_found_by_their_heartbeats(tmp_path) -> None:
    """A warm worker's environment is its pool's, without the attempt's token: the supervisor finds it by its
    heartbeat and waits until it is gone. A heartbeat's pid handed out again to another program is left alone."""
    beats, token = tmp_path / "heartbeat", f"attempt-{uuid.uuid4().hex}"
    env = {**os.environ, **attempt_env(beats, token, 1.0, 0, {})}
    named = "from ftrain.proctitle import name_process; name_process('rank 0/2 worker'); import time; time.sleep(600)"
    warm = launch([sys.executable, "-c", named], cwd=REPO, env=child_env())  # no token: as a fork of the pool
    stranger = launch(["sleep", "600"])
    wait_for(lambda: procfs.read(warm.pid, "comm").startswith(b"ftrain-r0of2"), "the worker named itself")
    for rank, pid in enumerate([warm.pid, stranger.pid]):
        beat = Heartbeat(rank, pid, 3, Phase.ROLLOUT, None, None, 1, 0.0)
        (beats / f"rank-{rank}.json").write_text(json.dumps(dataclasses.asdict(beat)))
    plan = Plan(generation=1, attempt=0, port=None)
    attempt = Attempt(plan, [sys.executable, "-c", "import time; time.sleep(600)"], env, token, tmp_path)
    try:
        assert sorted(attempt.processes()) == sorted([attempt.proc.pid, warm.pid])
        attempt.kill()
    finally:
        attempt.proc.kill()  # a no-op once killed
    assert warm.wait(timeout=10) == -signal.SIGKILL and attempt.proc.wait(timeout=10) == -signal.SIGKILL
    assert stranger.poll() is None, "a process that is no worker of the attempt"
