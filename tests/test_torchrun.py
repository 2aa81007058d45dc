"""ftrain's torchrun run by hand: a failure a worker explained is that one line and the worker's code; a crash keeps
torchrun's report. Real torchrun, real workers."""

from __future__ import annotations

import json
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ftrain import errorfile
from ftrain.supervise.attempt import TORCHRUN

from helpers import REPO, SMOKE, TESTS, as_a_terminal_starts_it, child_env, hooks_override, probe_hook

TYPO = "ftrain: error: unknown config key iteratons: did you mean iterations?"


SLOW_RANK_0 = """
import importlib.abc, os, runpy, sys, time

class SlowCli(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path, target=None):
        if name == "ftrain.cli":
            time.sleep(120)

if os.environ["RANK"] == "0":
    sys.meta_path.insert(0, SlowCli())
runpy.run_module("ftrain", run_name="__main__", alter_sys=True)
"""
"""``python -m ftrain`` whose rank 0 is still importing when the others have read their input: a loaded machine."""


def ftrun(
    tmp_path, *overrides: str, worker: tuple[str, ...] = ("-m", "ftrain"), launch: tuple[str, ...] = ("--standalone",)
) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", TORCHRUN, *launch, "--nproc-per-node=2", *worker, "train", SMOKE]
    return subprocess.run(
        [*command, "--storage", str(tmp_path / "run"), "log.console=false", *overrides],
        cwd=REPO,
        env=child_env({"PYTHONPATH": str(TESTS)}),
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_error_file_tells_a_failure_the_worker_explained_from_a_crash(tmp_path, monkeypatch) -> None:
    path = tmp_path / "error.json"
    monkeypatch.setenv(errorfile.ENV, str(path))
    monkeypatch.setenv("RANK", "1")  # records without printing
    errorfile.report("bad input")
    explained = json.loads(path.read_text())
    try:
        raise RuntimeError("a bug")
    except RuntimeError as error:
        errorfile.record_exception(error)
    crashed = json.loads(path.read_text())
    assert errorfile.reported(explained) and errorfile.message(explained) == "bad input"
    assert not errorfile.reported(crashed) and not errorfile.reported(None)


RECORDING_FOREVER = """
import sys
from ftrain import errorfile

try:
    raise RuntimeError("x" * 1_000_000)
except RuntimeError as error:
    errorfile.record_exception(error)
    print("recorded once", flush=True)
    while True:
        errorfile.record_exception(error)
"""
"""A worker that records a large exception over and over: killed at any moment, it is killed mid-write."""


def test_a_worker_killed_while_it_records_its_error_leaves_a_file_torchrun_can_read(tmp_path) -> None:
    """torchrun's agent reads a failed worker's error file and raises where it is not JSON, ending with a traceback
    and no account of any failure (CI: the supervisor SIGKILLed a rank that was recording its broken connection, and
    blamed 'torchrun exited with code 1'). Killed at random moments mid-write, the file holds the old record or the
    new one, whole."""
    from torch.distributed.elastic.multiprocessing.errors import ProcessFailure

    path = tmp_path / "error.json"
    moments = random.Random(52).choices([0.0, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05], k=30)
    for moment in moments:
        worker = subprocess.Popen(
            [sys.executable, "-c", RECORDING_FOREVER],
            cwd=REPO,
            env=child_env({errorfile.ENV: str(path)}),
            stdout=subprocess.PIPE,
        )
        assert worker.stdout.readline() == b"recorded once\n"
        time.sleep(moment)
        worker.send_signal(signal.SIGKILL)
        worker.wait()
        worker.stdout.close()
        failure = ProcessFailure(local_rank=0, pid=worker.pid, exitcode=-9, error_file=str(path))  # torchrun's read
        assert errorfile.message(failure.error_file_data) == "RuntimeError: " + "x" * 1_000_000
        path.unlink()
    print(f"{len(moments)} workers killed at random moments while they recorded: each error file whole")


@pytest.mark.slow
def test_a_typo_under_ftrains_torchrun_is_one_line_and_exit_2(tmp_path) -> None:
    result = ftrun(tmp_path, "iteratons=3")
    assert result.returncode == 2
    assert (result.stdout + result.stderr).splitlines() == [TYPO]


def test_a_typo_found_while_rank_0_still_imports_is_the_one_line(tmp_path) -> None:
    """torchrun stops rank 0 once rank 1 has refused the typo and ended: rank 0's stop is not news (CI saw "ftrain:
    stopped by SIGTERM" before the typo's line)."""
    script = tmp_path / "slow_rank_0.py"
    script.write_text(SLOW_RANK_0)
    result = ftrun(tmp_path, "iteratons=3", worker=(str(script),))
    assert result.returncode == 2
    assert (result.stdout + result.stderr).splitlines() == [TYPO]


@pytest.mark.slow
def test_a_crash_under_ftrains_torchrun_keeps_torchruns_report(tmp_path) -> None:
    crash = hooks_override(probe_hook("CrashingHook", path=tmp_path / "crashed", rank=1, iteration=1))
    result = ftrun(tmp_path, "iterations=3", crash)
    assert result.returncode == 1
    assert "ChildFailedError" in result.stderr and "RuntimeError: probe crash after iteration 1" in result.stderr


@pytest.mark.slow
def test_an_elastic_launch_refuses_at_its_start_a_total_that_a_larger_world_cannot_share(tmp_path) -> None:
    """``--nnodes 1:2`` of 2 ranks each: the run starts at 2 ranks, which share 6 environments, but a second node
    would make 4, which do not. Refused before anything is made, not when the node joins."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    elastic = ("--nnodes=1:2", "--rdzv-backend=c10d", f"--rdzv-endpoint=127.0.0.1:{port}")
    result = ftrun(tmp_path, "env.total_envs=6", launch=(*elastic, "--rdzv-conf=last_call_timeout=1"))
    refused = "env.total_envs=6 cannot be shared evenly by the 4 ranks of 2 nodes (--nnodes 1:2, 2 per node)"
    assert result.returncode == 2, result.stderr[-3000:]
    assert (result.stdout + result.stderr).splitlines() == [
        f"ftrain: error: {refused}: set a total that every world divides (env.total_envs=4), or env.num_envs=N to "
        "count per rank"
    ]
    assert not (tmp_path / "run").exists()  # refused before the storage was taken: nothing made (its lease, locks)


@pytest.mark.slow
@pytest.mark.parametrize("stop", [signal.SIGTERM, signal.SIGHUP])
def test_a_stop_while_waiting_for_a_rendezvous_host_that_is_not_up_ends_at_once_in_one_line(tmp_path, stop) -> None:
    """Node 1 of 2 waits for node 0's address, where nothing listens yet: torch's TCPStore retries its connect through
    a signal for up to 15 minutes (a C++ trace each time), so a stop there did nothing. Now it ends within seconds with
    143 and one line; there is nothing to save."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    launch = ["--nnodes=2", "--node-rank=1", "--nproc-per-node=1", "--master-addr=127.0.0.1", f"--master-port={port}"]
    command = [sys.executable, "-m", TORCHRUN, *launch, "-m", "ftrain", "train", SMOKE, "--storage", str(tmp_path)]
    proc = subprocess.Popen(
        command,
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        preexec_fn=as_a_terminal_starts_it,
    )
    maps = Path(f"/proc/{proc.pid}/maps")
    deadline = time.monotonic() + 120
    while "libtorch_python" not in maps.read_text() and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(3)  # torch imported; then torchrun's rendezvous, in its connect to the host that is not up
    proc.send_signal(stop)
    try:
        code = proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise AssertionError(f"still waiting 30 s after {stop.name}: {proc.stderr.read().decode()[-2000:]}") from None
    said = proc.stderr.read().decode()
    assert (code, said.splitlines()[-1:]) == (143, ["ftrain: stopped by SIGTERM"]), said[-2000:]


@pytest.mark.slow
@pytest.mark.parametrize(
    ("told", "storage", "said"),
    [
        (["seed=7", "algorithm.clip_param=0.1"], "run", "algorithm.clip_param 0.2 -> 0.1; seed 1 -> 7"),
        (["iterations=9"], "run", "iterations 8 -> 9"),
        ([], "other", "storage {run} -> {other}"),
    ],
    ids=["training-keys", "length", "storage"],
)
def test_nodes_started_with_another_run_are_refused_before_anything_is_taken(tmp_path, told, storage, said) -> None:
    """Two nodes of one rank each, started apart, node 1 told another training key, length or storage: they trained
    together in silence (their checkpoints claiming rank 0's config), or, on two storages, trained the whole run
    without one commit and then held for an hour. Refused on both nodes in one line, nothing made in either storage."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    paths = {"run": str(tmp_path / "run"), "other": str(tmp_path / "other")}
    nodes = []
    for node, (overrides, where) in enumerate([([], "run"), (told, storage)]):
        launch = ["--nnodes=2", f"--node-rank={node}", "--nproc-per-node=1", "--master-addr=127.0.0.1"]
        command = [sys.executable, "-m", TORCHRUN, *launch, f"--master-port={port}", "-m", "ftrain", "train", SMOKE]
        command += ["--storage", paths[where], "log.console=false", *overrides]
        nodes.append(subprocess.Popen(command, cwd=REPO, env=child_env(), stderr=subprocess.PIPE, text=True))
    ended = [(proc.wait(timeout=180), proc.stderr.read()) for proc in nodes]
    line = (
        f"ftrain: error: rank 1 was started with another run than rank 0: {said.format(**paths)} (rank 0's -> rank "
        "1's): start every node with the same config, overrides and --storage"
    )
    for code, stderr in ended:
        assert (code, stderr.splitlines()) == (2, [line]), stderr[-3000:]
    assert not (tmp_path / "run").exists() and not (tmp_path / "other").exists()
