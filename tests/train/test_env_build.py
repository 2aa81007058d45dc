"""Building the environments, the step of a start that grows with the input: a build that would not fit in memory is
refused after its first environments with one line that names the setting and a value that fits; a stop while it
builds ends the run at once with the stop's code. Real processes, real MuJoCo, real signals."""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import time

import pytest

from ftrain import procfs
from ftrain.train.env_build import SHARE, BuildWatch, TooLarge

from helpers import REPO, child_env, events, finish, launch, manifests, supervise_command, train_command, wait_for


def refusal(per_env: float, available: int, total: int, setting: tuple[str, int], ranks_here: int) -> str | None:
    watch = BuildWatch(total, setting, ranks_here, print)
    try:
        watch._check_memory(per_env, available)
    except TooLarge as refused:
        return str(refused)
    return None


def test_a_build_is_refused_exactly_when_it_would_not_fit_and_the_value_it_suggests_fits() -> None:
    """Generated cases (environment sizes, memory, ranks on the machine, ``env.num_envs`` or ``env.total_envs`` over
    a world): refused if and only if the environments need more than ``SHARE`` of the memory available, and the
    value the line suggests fits, where one more environment per rank would not."""
    draw, refused = random.Random(), 0
    seed = draw.randrange(2**32)
    draw.seed(seed)
    for _ in range(500):
        per_env, available = draw.uniform(2e4, 5e6), draw.randint(10**8, 10**11)
        ranks_here, world = draw.randint(1, 8), draw.choice([1, 2, 4, 8])
        per_rank = draw.randint(1, 3 * int(SHARE * available / (per_env * ranks_here)) + 2)
        setting = ("env.total_envs", per_rank * world) if draw.random() < 0.5 else ("env.num_envs", per_rank)
        line = refusal(per_env, available, per_rank, setting, ranks_here)
        assert (line is not None) == (per_env * per_rank * ranks_here > SHARE * available), (seed, line)
        if line is None:
            continue
        refused += 1
        name, value = setting
        assert line.startswith(f"{name}={value}: its environments need about "), line
        suggested = int(re.search(rf"use {re.escape(name)}=(\d+) or fewer$", line)[1])
        suggested_per_rank = suggested * per_rank // value
        assert refusal(per_env, available, suggested_per_rank, (name, suggested), ranks_here) is None, (seed, line)
        over = refusal(per_env, available, suggested_per_rank + 1, (name, suggested), ranks_here)
        assert over is not None, (seed, line)
    print(f"500 generated cases (seed {seed}): {refused} refused, each suggestion fits")


PEAK_MEMORY = """
import resource, subprocess, sys
code = subprocess.run(sys.argv[1:]).returncode
print(f"peak kB: {resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}", file=sys.stderr)
sys.exit(code)
"""
"""Runs the command after it and prints, last, the most memory it held (of this process's children: that one)."""


def too_many_environments(ranks_here: int) -> int:
    """Ten times what fits in the memory this machine has now, at about 1 MB per environment."""
    return 10 * procfs.available_memory() // (10**6 * ranks_here)


@pytest.mark.slow
def test_environments_that_would_not_fit_are_refused_before_they_take_the_memory(tmp_path) -> None:
    """A probe asked for 200,000 environments and grew 230 MB/s into a machine-wide OOM kill. Now: one line naming
    the setting and a value that fits, exit 2, under 2 GB of memory ever taken, nothing written as a step; under the
    supervisor (two ranks, ``env.total_envs``) not restarted, as any bad input."""
    num_envs = too_many_environments(1)
    command = [sys.executable, "-c", PEAK_MEMORY, *train_command(tmp_path / "run", f"env.num_envs={num_envs}")]
    done = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    said, _, peak = done.stderr.rpartition("peak kB: ")
    assert done.returncode == 2, done.stderr[-2000:]
    line = f"ftrain: error: env.num_envs={num_envs}: its environments need about "
    assert said.startswith(line) and said.count("\n") == 1, done.stderr[-2000:]
    assert re.search(r"\(\d+\.\d MB each, 1 rank\), and this machine has .* use env.num_envs=\d+ or fewer\n$", said)
    assert int(peak) < 2 * 1024**2, f"{peak} kB: the build went on"
    assert not manifests(tmp_path / "run")

    total = 2 * too_many_environments(2)
    storage = tmp_path / "supervised"
    proc = launch(
        supervise_command(storage, f"env.total_envs={total}"),
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert finish(proc, timeout=120) == 2
    printed = proc.stdout.read()
    assert f"refused its input: env.total_envs={total}: " in printed and "2 ranks on this machine" in printed, printed
    assert "bad input (exit 2): 0 restarts" in printed, printed
    assert [event["event"] for event in events(storage)][-2:] == ["usage", "summary"]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("supervised", "stop"), [(False, signal.SIGINT), (True, signal.SIGTERM)], ids=["train-sigint", "supervise-sigterm"]
)
def test_a_stop_while_the_environments_are_built_ends_the_run_at_once(tmp_path, supervised, stop) -> None:
    """A probe's SIGTERM went unanswered while a large build ran (nothing looked at the stop request before the
    trainer existed). Now the build ends at the next environment and every rank exits with the stop's code: sent at a
    random moment of the build (printed), the run ends within seconds, with nothing to save and nothing saved."""
    storage, output = tmp_path / "run", tmp_path / "output.txt"
    slow_build = "env.num_envs=5000"  # said (SAY_FROM), and seconds to build: a stop comes while it builds
    command = supervise_command(storage, slow_build) if supervised else train_command(storage, slow_build)
    with output.open("w") as sink:
        proc = launch(command, cwd=REPO, env=child_env(), stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
    wait_for(lambda: "[ftrain] building 5,000 environments per rank: about" in output.read_text(), "the build's line")
    moment = random.uniform(0.0, 2.0)
    time.sleep(moment)
    proc.send_signal(stop)
    assert finish(proc, timeout=30, output=output) == 128 + stop, output.read_text()[-2000:]
    printed = output.read_text()
    name = "SIGINT" if stop == signal.SIGINT else "SIGTERM to the supervisor"
    assert f"[ftrain] stopped by {name} while starting, before any training: nothing to save" in printed, printed
    assert "Traceback" not in printed, printed[-3000:]
    assert not manifests(storage)
    if supervised:
        assert "preempted: the workers stopped before training began (no step committed yet)" in printed, printed
    print(f"stopped {moment:.2f} s into the build")


@pytest.mark.slow
def test_a_stop_to_one_rank_while_starting_ends_every_rank_at_once(tmp_path) -> None:
    """A probe's SIGTERM to rank 1 of two while they started: rank 1 ended, and rank 0, waiting in C for it (a
    collective, a rendezvous), left torchrun's SIGTERM unanswered until its SIGKILL 30 s later, and torchrun ended 1
    with a traceback. Now a stop before training ends a rank at once whatever it waits in: here within 20 s (about
    3 s measured), with the stop's code and rank 0's line."""
    output = tmp_path / "output.txt"
    command = [
        sys.executable,
        "-m",
        "ftrain.torchrun",
        *train_command(tmp_path / "run", "env.num_envs=3000", ranks=2)[3:],
    ]
    with output.open("w") as sink:
        proc = launch(command, cwd=REPO, env=child_env(), stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
    wait_for(lambda: "environments per rank: about" in output.read_text(), "the build's line")

    def rank_1() -> int | None:
        found = [pid for pid in procfs.descendants(proc.pid) if b"rank 1/2 worker" in procfs.read(pid, "cmdline")]
        return found[0] if found else None

    worker = wait_for(rank_1, "rank 1's worker")
    signalled = time.monotonic()
    os.kill(worker, signal.SIGTERM)
    assert finish(proc, timeout=60, output=output) == 143, output.read_text()[-2000:]
    ended = time.monotonic() - signalled
    printed = output.read_text()
    assert ended < 20, f"{ended:.1f} s: a rank waited for torchrun's SIGKILL\n{printed[-2000:]}"
    assert "stopped by SIGTERM while starting, before any training: nothing to save" in printed, printed[-2000:]
    assert "Traceback" not in printed and not manifests(tmp_path / "run"), printed[-2000:]
    print(f"every rank ended {ended:.1f} s after rank 1's SIGTERM")


def test_a_stop_to_one_supervised_rank_while_starting_is_blamed_on_that_rank(tmp_path) -> None:
    """A probe's SIGTERM to rank 1's stand-in while the supervised ranks built their environments: both ended with
    143 (rank 0 stopped by torchrun after rank 1 ended), and the supervisor's cause named rank 0, the lowest of two
    alike. A rank stopped while starting records its stop with the time: the first to stop is named."""
    storage = tmp_path / "run"
    output = tmp_path / "output.txt"
    with output.open("w") as sink:
        command = supervise_command(storage, "env.num_envs=3000")
        command[5:5] = ["--max-restarts", "0"]  # after --nproc-per-node: the rank's failure ends the run
        proc = launch(command, cwd=REPO, env=child_env(), stdout=sink, stderr=subprocess.STDOUT)
    wait_for(lambda: "environments per rank: about" in output.read_text(), "the build's line")
    (stand_in,) = [pid for pid in procfs.descendants(proc.pid) if b"rank 1/2 stand-in" in procfs.read(pid, "cmdline")]
    os.kill(stand_in, signal.SIGTERM)
    finish(proc, timeout=120, output=output)
    (exit_event,) = [event for event in events(storage) if event["event"] == "exit"]
    assert exit_event["cause"].startswith("rank 1 exited with code 143: stopped by SIGTERM while starting"), exit_event
    assert "traceback in" not in exit_event["cause"], exit_event
