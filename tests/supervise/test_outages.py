"""Outages of the storage, without mocks: a supervised 2-rank run on S3 (moto's server behind a proxy the test
switches) waits out a refusing port with torchrun killed inside it, and a hanging server with a worker killed inside
it, and ends with exit 0 and the same ``state_sha256`` as an uninterrupted run. Outages are 15 s here (the issue's
45 s and 90 s belong to launch/bench_chaos.py); lowered timeouts keep the waits short."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ftrain.ckpt.steps import select_resume
from ftrain.ckpt.storage import Storage

from helpers import REPO, child_env, events, final_manifest, finish, launch, torchrun_pid, training, wait_for

pytestmark = pytest.mark.slow

OUTAGE = 15.0
ITERATIONS = 300
OVERRIDES = [
    f"iterations={ITERATIONS}",
    "checkpoint.interval=10",
    "checkpoint.max_unsaved=30",  # the outage outlasts it: training holds, then goes on
    "checkpoint.retries=1",
    "storage.options.config_kwargs={connect_timeout: 2, read_timeout: 3}",
    "dist_timeout=20",
    "log.console=false",
]
OPTIONS = ["--nproc-per-node", "2", "--backoff-initial", "0.2", "--stop-grace", "3"]


def start(storage: str | Path, logs: Path, env: dict | None = None) -> subprocess.Popen:
    command = [sys.executable, "-m", "ftrain", "supervise", *OPTIONS, "configs/smoke.yaml", "--storage", str(storage)]
    output = open(f"{logs}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
    overrides = [*OVERRIDES, f"log_dir={logs}"]
    return launch([*command, *overrides], cwd=REPO, env=child_env(env), stdout=output, stderr=subprocess.STDOUT)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> str:
    """``state_sha256`` of an uninterrupted supervised run (local storage: the state does not depend on it)."""
    root = tmp_path_factory.mktemp("reference")
    assert finish(start(root / "run", root / "logs")) == 0
    return final_manifest(root / "run")["state_sha256"]


def wait_event(logs: Path, name: str) -> dict:
    return wait_for(lambda: next((e for e in events(logs) if e["event"] == name), None), f"a {name} event")


def assert_waited_out(proc: subprocess.Popen, outage, logs: Path, reference: str) -> None:
    assert finish(proc, timeout=300) == 0, Path(f"{logs}.log").read_text()[-3000:]
    names = [event["event"] for event in events(logs)]
    assert "storage_wait" in names and "storage_back" in names
    assert "usage" not in names and "crash_loop" not in names
    step, manifest = select_resume(Storage.open(outage.url, outage.options), log=lambda line: None)
    assert step == ITERATIONS and manifest["state_sha256"] == reference


def test_a_refusing_storage_with_torchrun_killed_inside_the_outage_is_waited_out(tmp_path, s3_outage, reference):
    logs = tmp_path / "logs"
    proc = start(s3_outage.url, logs, s3_outage.env)
    training(logs / "heartbeat", 20)
    s3_outage.server.refuse()
    began = time.monotonic()
    time.sleep(2)  # saves fail, training goes on, then holds past max_unsaved
    os.kill(torchrun_pid(proc.pid), signal.SIGKILL)
    waiting = wait_event(logs, "storage_wait")
    assert "cannot reach the S3 endpoint" in waiting["cause"]
    time.sleep(max(0.0, began + OUTAGE - time.monotonic()))
    s3_outage.server.restore()
    assert_waited_out(proc, s3_outage, logs, reference)


def test_a_hanging_storage_with_a_worker_killed_inside_the_outage_is_waited_out(tmp_path, s3_outage, reference):
    logs = tmp_path / "logs"
    proc = start(s3_outage.url, logs, s3_outage.env)
    beats = training(logs / "heartbeat", 20)
    s3_outage.server.hang()
    began = time.monotonic()
    time.sleep(2)
    os.kill(beats[1].pid, signal.SIGKILL)
    wait_event(logs, "storage_wait")
    time.sleep(max(0.0, began + OUTAGE - time.monotonic()))
    s3_outage.server.unhang()
    assert_waited_out(proc, s3_outage, logs, reference)
