"""Chaos: supervised 2-rank runs of configs/smoke.yaml, hit from outside by real signals, must end with the same
``state_sha256`` as an uninterrupted run, and ``events.jsonl`` must show every detection.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ftrain import procfs
from ftrain.errors import EXIT_PREEMPTED
from ftrain.supervise.auth import SECRET_ENV

from helpers import (
    REPO,
    assert_all_nodes_restarted_once,
    child_env,
    events,
    final_manifest,
    finish,
    flip_byte,
    free_port,
    launch,
    torchrun_pid,
    training,
    wait_for,
)

pytestmark = pytest.mark.slow

CONFIG = "configs/smoke.yaml"
OVERRIDES = ["iterations=100", "dist_timeout=30", "log.console=false"]  # longer than the hang timeout
DEFAULTS = ["--nproc-per-node", "2", "--backoff-initial", "0.2", "--stop-grace", "20"]


def start(storage: Path, *options: str, log: str = "supervise", env: dict | None = None) -> subprocess.Popen:
    """``ftrain supervise`` (2 ranks, unless in ``options``) on ``storage``; output: ``<storage>.<log>.log``."""
    command = [sys.executable, "-m", "ftrain", "supervise", *DEFAULTS, *options, CONFIG, "--storage", str(storage)]
    output = open(f"{storage}.{log}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
    return launch([*command, *OVERRIDES], cwd=REPO, env=child_env(env), stdout=output, stderr=subprocess.STDOUT)


def after(recovered: dict) -> int:
    """The step a recovery resumed from: None when it restarted from nothing (no checkpoint was committed yet)."""
    return recovered["step"] or 0


def wait_event(storage: Path, name: str, count: int) -> dict:
    def found():
        matching = [event for event in events(storage) if event["event"] == name]
        return matching[count - 1] if len(matching) >= count else None

    return wait_for(found, f"{count} {name} events", interval=0.05)  # each look re-reads the whole log


@pytest.fixture
def reference(reference_state) -> str:
    """The state an uninterrupted run of cold workers (each a fresh Python process) ends on: the chaos runs, of warm
    workers (forked from the warm pool, the default), must end on the same bits."""
    return reference_state(100)


def test_chaos_ends_bit_for_bit_like_an_uninterrupted_run(tmp_path, reference):
    storage = tmp_path / "run"
    heartbeats = storage / "heartbeat"
    proc = start(storage, "--hang-timeout", "10")  # a loaded machine slows no phase that long; a SIGSTOP is found

    # 1. SIGKILL of one worker
    beats = training(heartbeats, 4)
    pool = int(procfs.stat_fields(beats[1].pid)[1])
    # each process says what it is in ps: a warm worker, forked by the pool, which the supervisor started
    assert procfs.read(beats[1].pid, "cmdline").startswith(b"ftrain: rank 1/2 worker (run smoke)")
    assert procfs.read(pool, "cmdline").startswith(f"ftrain: warm pool of supervisor {proc.pid}".encode())
    assert procfs.read(proc.pid, "cmdline").startswith(b"ftrain: supervisor (run smoke)")
    assert procfs.read(torchrun_pid(proc.pid), "cmdline").startswith(b"ftrain: torchrun stand-in")
    # their short names have no space: SLURM's proctrack/linuxproc splits /proc/<pid>/stat at spaces
    assert [procfs.read(pid, "comm") for pid in (proc.pid, pool, beats[1].pid)] == [
        b"ftrain-supervis\n",
        b"ftrain-warm-poo\n",
        b"ftrain-r1of2-wo\n",
    ]
    os.kill(beats[1].pid, signal.SIGKILL)
    recovered = wait_event(storage, "recovered", 1)

    # 2. SIGKILL of the torchrun agent: its workers are orphans, they save on the supervisor's SIGTERM
    training(heartbeats, after(recovered) + 3)
    os.kill(torchrun_pid(proc.pid), signal.SIGKILL)
    recovered = wait_event(storage, "recovered", 2)

    # 3. SIGSTOP of one worker: a hang
    beats = training(heartbeats, after(recovered) + 3)
    os.kill(beats[0].pid, signal.SIGSTOP)
    recovered = wait_event(storage, "recovered", 3)

    # 4. the newest checkpoint corrupted before the restart: freeze both ranks (and so their writer threads), flip a
    # byte of rank 1's shard in it and in any newer step (a save in flight, whose commit rank 0 makes once it runs
    # again: it then records the digest of what rank 1 wrote, not of the byte flipped), kill rank 1
    beats = training(heartbeats, after(recovered) + 5)
    for beat in beats.values():
        os.kill(beat.pid, signal.SIGSTOP)
    corrupted = final_manifest(storage)["step"]
    for step in (storage / "checkpoints").glob("step-*"):
        shard = step / "rank-00001.pt"
        if int(step.name.removeprefix("step-")) >= corrupted and shard.exists() and shard.stat().st_size:
            flip_byte(shard)
    os.kill(beats[1].pid, signal.SIGKILL)
    with contextlib.suppress(ProcessLookupError):  # torchrun may have seen rank 1 die and ended rank 0 already
        os.kill(beats[0].pid, signal.SIGCONT)
    recovered = wait_event(storage, "recovered", 4)
    assert after(recovered) < corrupted

    # 5. SIGTERM to every process of the run at once, as SLURM stops a job step (the supervisor, the warm pool,
    # torchrun, the workers and their stand-ins): the workers save, it exits 143; the same command continues
    training(heartbeats, after(recovered) + 3)
    for pid in [proc.pid, *procfs.descendants(proc.pid)]:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGTERM)
    assert finish(proc) == EXIT_PREEMPTED
    saved = final_manifest(storage)["step"]
    assert finish(start(storage, log="rerun")) == 0

    manifest = final_manifest(storage)
    step = manifest["step"]
    assert (step, manifest["state_sha256"]) == (100, reference)
    log = events(storage)
    causes = [event["cause"] for event in log if event["event"] == "exit"]
    assert causes[:4] == [
        "rank 1 killed by SIGKILL",
        "torchrun killed by SIGKILL",
        "killed: rank 0 hung",
        "rank 1 killed by SIGKILL",
    ]
    hangs = [event for event in log if event["event"] == "hang"]
    assert len(hangs) == 1 and hangs[0]["processes"]["0"] == "T" and hangs[0]["limit"] == 10
    preempted = [event for event in log if event["event"] == "preempted"]
    assert len(preempted) == 1
    resumed = [event["step"] for event in log if event["event"] == "resumed"]
    assert resumed[-1] == saved  # the rerun lost nothing
    summary = [event for event in log if event["event"] == "summary"]
    assert [event["restarts"] for event in summary] == [4, 0]


def test_two_nodes_both_recover_when_one_loses_its_worker(tmp_path, reference):
    storage = tmp_path / "run"
    endpoint = f"127.0.0.1:{free_port()}"
    nodes = [
        start(
            storage,
            "--nproc-per-node",
            "1",
            "--nnodes",
            "2",
            "--node-rank",
            str(node),
            "--rdzv-endpoint",
            endpoint,
            "--hang-timeout",  # not auto's 5 s floor: a phase slowed that long by a loaded machine is no hang here
            "60",
            log=f"node{node}",
            env={SECRET_ENV: "ftrain-test-chaos-secret"},
        )
        for node in (0, 1)
    ]
    beats = training(storage / "heartbeat" / "node-1", 4, ranks=[1])
    os.kill(beats[1].pid, signal.SIGKILL)
    assert [finish(node) for node in nodes] == [0, 0]
    manifest = final_manifest(storage)
    step = manifest["step"]
    assert (step, manifest["state_sha256"]) == (100, reference)
    log = events(storage)
    assert_all_nodes_restarted_once(log)
    assert any(event["event"] == "exit" and event["cause"] == "rank 1 killed by SIGKILL" for event in log)
