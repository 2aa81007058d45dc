"""No orphans: whatever ends ``ftrain supervise`` (SIGKILL included), its torchrun and workers end within seconds;
a plain torchrun run knows no supervisor, and its workers save and exit once their torchrun is gone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from ftrain import lifeline, procfs

from helpers import (
    REPO,
    SMOKE,
    child_env,
    final_manifest,
    launch,
    manifests,
    metrics_by_iteration,
    run_train,
    start_train,
    torchrun_pid,
    training,
    wait_for,
)

ITERATIONS = 100
"""The plain run's length, as long as the shared reference run of other tests: its torchrun is killed after 3."""
ORPHAN_DEADLINE = 15.0
"""Seconds after the supervisor's death by which no process of its run may be left (the issue's bound)."""


def alive(pid: int) -> bool:
    return procfs.stat_fields(pid)[:1] not in ([], ["Z"], ["X"])


def tie(supervisor_env: dict[str, str]) -> subprocess.CompletedProcess:
    """A process that ties itself to the supervisor ``supervisor_env`` names, as torchrun does, then says so."""
    code = "from ftrain import lifeline; lifeline.die_with_supervisor(); print('tied')"
    return subprocess.run(
        [sys.executable, "-c", code], env=child_env(supervisor_env), capture_output=True, text=True, timeout=60
    )


def test_torchrun_ties_itself_to_its_parent_only():
    """The tie is made to the parent that names itself; a process whose named supervisor is not its parent (the
    supervisor ended before the tie, and the orphan was taken over by another process) ends at once."""
    assert tie(lifeline.supervisor_env()).stdout == "tied\n"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        stranger = {lifeline.SUPERVISOR_ENV: f"{other.pid}:{procfs.start_time(other.pid)}"}
        assert tie(stranger).returncode == -signal.SIGKILL
    finally:
        other.kill()
        other.wait()
    assert tie({}).stdout == "tied\n"  # no supervisor (plain torchrun): nothing to tie to


@pytest.mark.slow
@pytest.mark.waits  # waits for the orphans to notice: under 10% of it on the CPU
def test_a_sigkilled_supervisor_leaves_no_process_of_its_run(tmp_path):
    """One worker is stopped (SIGSTOP) first: no thread of its own can end it, its siblings must."""
    run = tmp_path / "run"
    command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "2", SMOKE, "--storage", str(run)]
    command += ["iterations=100000", "log.console=false"]
    supervisor = launch(command, cwd=REPO, env=child_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    beats = training(run / "heartbeat", 3)
    agent = torchrun_pid(supervisor.pid)
    run_processes = procfs.descendants(supervisor.pid)  # torchrun, the workers, the warm pool and its forks
    assert {agent, *(beat.pid for beat in beats.values())} <= set(run_processes)
    os.kill(beats[1].pid, signal.SIGSTOP)

    supervisor.kill()
    killed = time.monotonic()
    supervisor.wait()
    try:
        wait_for(lambda: not any(map(alive, run_processes)), "the run's processes to end", ORPHAN_DEADLINE, 0.05)
    finally:  # a failed test leaves no orphans either
        for pid in filter(alive, run_processes):
            os.kill(pid, signal.SIGKILL)
    print(f"every process of the run ended {time.monotonic() - killed:.2f} s after the supervisor's SIGKILL")


@pytest.mark.slow
def test_the_workers_of_a_sigkilled_plain_torchrun_save_and_exit_and_the_next_launch_ends_on_the_same_bits(
    tmp_path, reference_state
):
    """Without a supervisor, workers whose torchrun ends stop as torchrun would have stopped them: they save and exit,
    where they trained on unseen and held the storage against the next launch, which resumes from that save and ends
    as the run uninterrupted. Only the stop saves (no interval)."""
    run = tmp_path / "run"
    agent = start_train(run, f"iterations={ITERATIONS}", "checkpoint.interval=100000", ranks=2)
    try:
        wait_for(lambda: (run / "metrics.csv").exists() and len(metrics_by_iteration(run)) >= 3, "3 iterations", 180)
    finally:
        workers = procfs.descendants(agent.pid)
        agent.kill()
        agent.wait()
    killed = time.monotonic()
    try:
        assert len(workers) == 2, workers
        wait_for(lambda: not any(map(alive, workers)), "the workers to save and exit", ORPHAN_DEADLINE, 0.05)
    finally:  # a failed test leaves no orphans either
        for pid in filter(alive, workers):
            os.kill(pid, signal.SIGKILL)
    exited = time.monotonic() - killed
    (saved,) = manifests(run)  # the stop's save, verified
    print(f"both workers saved step {saved} and exited {exited:.2f} s after torchrun's SIGKILL")
    assert 3 <= saved < ITERATIONS

    resumed = run_train(run, f"iterations={ITERATIONS}", ranks=2)
    assert f"resumed from step {saved}" in resumed.stdout + resumed.stderr
    assert final_manifest(run)["state_sha256"] == reference_state(ITERATIONS)
