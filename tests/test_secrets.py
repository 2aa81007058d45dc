"""Credentials never reach anything ftrain persists or prints: a supervised run on one and on two nodes, a run refused
by the lease, every ``ftrain ckpt`` action (an error too), ``ftrain play`` and ``ftrain export``, grepped on stdout
and stderr of every process, in every file they wrote and in every object of the storage.

The S3 credentials travel in the storage URL (``s3://KEY:SECRET@bucket/run``) and in ``storage.options``; the
two-node run also has its coordinator secret. None of them may show up anywhere, nor on the command line of a
process the supervisor starts.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ftrain import procfs
from ftrain.ckpt.lease import Lease
from ftrain.ckpt.storage import Storage
from ftrain.errors import EXIT_PREEMPTED, EXIT_STORAGE_HELD

from helpers import (
    REPO,
    SMOKE,
    child_env,
    create_bucket,
    events,
    finish,
    free_port,
    launch,
    s3_client,
    torchrun_pid,
    training,
    wait_for,
)

pytestmark = pytest.mark.slow

RDZV_SECRET = "ftrain-test-rdzv-secret-Hx3kQ8zR"


def run_url(s3_server: dict, bucket: str) -> str:
    return f"s3://{s3_server['key']}:{s3_server['secret']}@{bucket}/run"


def start_supervise(
    s3_server: dict, url: str, log_dir: Path, *options: str, env: dict | None = None, overrides: tuple[str, ...] = ()
) -> tuple[subprocess.Popen, Path]:
    """Start ``ftrain supervise`` on a smoke run (2 iterations unless ``overrides`` say otherwise), the S3 endpoint
    and credentials in ``storage.options``; its console output goes to the file returned."""
    storage_options = (
        f"storage.options={{endpoint_url: '{s3_server['endpoint_url']}', "
        f"key: {s3_server['key']}, secret: {s3_server['secret']}}}"
    )
    command = [sys.executable, "-m", "ftrain", "supervise", *options, SMOKE, "--storage", url, storage_options]
    command += ["iterations=2", f"log_dir={log_dir}", "log.tensorboard=true", *overrides]
    console = Path(f"{log_dir}.console")
    with console.open("wb") as output:
        return launch(command, cwd=REPO, env=child_env(env), stdout=output, stderr=subprocess.STDOUT), console


def supervise(s3_server: dict, url: str, log_dir: Path, *options: str, env: dict | None = None, expect: int = 0):
    """``start_supervise``; returns a function that waits for its exit (``expect``) and gives back everything it
    printed."""
    proc, console = start_supervise(s3_server, url, log_dir, *options, env=env)

    def printed() -> str:
        code = finish(proc, timeout=300)
        assert code == expect, console.read_text()[-3000:]
        return console.read_text()

    return printed


def command(*args: str, env: dict, expect: int = 0) -> str:
    done = subprocess.run(
        [sys.executable, "-m", "ftrain", *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == expect, f"{args}: {done.returncode}\n{done.stderr[-3000:]}"
    return done.stdout + done.stderr


def test_no_command_persists_or_prints_credentials(tmp_path, s3_server) -> None:
    secrets = [s3_server["key"], s3_server["secret"], RDZV_SECRET]
    printed: dict[str, str] = {}

    one = run_url(s3_server, create_bucket(s3_server))
    printed["supervise"] = supervise(s3_server, one, tmp_path / "one", "--nproc-per-node", "2")()

    two = run_url(s3_server, create_bucket(s3_server))
    endpoint = f"127.0.0.1:{free_port()}"
    nodes = [
        supervise(
            s3_server,
            two,
            tmp_path / "two",
            *("--nnodes", "2", "--node-rank", str(node), "--rdzv-endpoint", endpoint),
            env={"FTRAIN_RDZV_SECRET": RDZV_SECRET},
        )
        for node in (0, 1)
    ]
    for node, node_printed in enumerate(nodes):
        printed[f"supervise node {node}"] = node_printed()

    # the credentials come from the URL alone from here on: only the endpoint is in the environment
    env = child_env({"AWS_ENDPOINT_URL": s3_server["endpoint_url"]})
    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN"):
        env.pop(name, None)
    step = f"{one}/checkpoints/step-000000002"
    printed["ckpt ls"] = command("ckpt", "ls", one, env=env)
    printed["ckpt verify"] = command("ckpt", "verify", one, env=env)
    printed["ckpt show"] = command("ckpt", "show", step, env=env)
    printed["ckpt show --json"] = command("ckpt", "show", one, "--json", env=env)
    printed["ckpt prune"] = command("ckpt", "prune", one, "--keep-last", "1", "--dry-run", env=env)
    printed["ckpt show missing"] = command("ckpt", "show", f"{one}/checkpoints/step-000000099", env=env, expect=2)
    printed["play"] = command("play", one, "--episodes", "1", env=env)
    printed["export"] = command("export", step, "--format", "torchscript", "-o", str(tmp_path / "p.pt"), env=env)

    # the lease's refusal of a second run while one holds the storage (this process, with the same credentials)
    holder = Lease(Storage.open(one, {"endpoint_url": s3_server["endpoint_url"]}), "holder", print)
    holder.acquire()  # alive: this process runs (acquire, not hold: its children would inherit the run)
    try:
        printed["supervise refused"] = supervise(
            s3_server, one, tmp_path / "refused", "--nproc-per-node", "1", expect=EXIT_STORAGE_HELD
        )()
    finally:
        holder.release()
    assert "is held by another run (holder" in printed["supervise refused"]

    assert "step-000000099" in printed["ckpt show missing"]  # the error names the URL, without its credentials
    for what, text in printed.items():
        for secret in secrets:
            assert secret not in text, f"{what} printed a credential:\n{text}"
    files = [path for path in tmp_path.rglob("*") if path.is_file()]
    assert any(path.name == "events.jsonl" for path in files)
    for path in files:
        data = path.read_bytes()
        for secret in secrets:
            assert secret.encode() not in data, f"a credential leaked into {path.relative_to(tmp_path)}"
    stored = bucket_objects(s3_server, one) | bucket_objects(s3_server, two)  # manifests, shards, LEASE, FENCE...
    assert {"run/LEASE.json", "run/FENCE.json"} <= {name.partition("/")[2] for name in stored}, sorted(stored)
    for name, data in stored.items():
        for secret in secrets:
            assert secret.encode() not in data, f"a credential leaked into the storage's {name}"


def bucket_objects(s3_server: dict, url: str) -> dict[str, bytes]:
    """Every object of the bucket of ``url``, by ``bucket/key``."""
    bucket, client = url.rpartition("@")[2].partition("/")[0], s3_client(s3_server)
    pages = client.get_paginator("list_objects_v2").paginate(Bucket=bucket)
    keys = [item["Key"] for page in pages for item in page.get("Contents", [])]
    return {f"{bucket}/{key}": client.get_object(Bucket=bucket, Key=key)["Body"].read() for key in keys}


def test_workers_get_credentials_off_the_command_line(tmp_path, s3_server) -> None:
    """Every user of the machine reads every command line (``ps``): the supervisor's torchrun and workers get the
    credentials (in the URL, in a mapping override, in dotted overrides) through their environment instead, which
    only their user reads, and train with them."""
    secrets = [s3_server["key"], s3_server["secret"]]
    dotted = [f"storage.options.key={s3_server['key']}", f"storage.options.secret={s3_server['secret']}"]
    url = run_url(s3_server, create_bucket(s3_server))
    log_dir = tmp_path / "run"
    proc, console = start_supervise(
        s3_server, url, log_dir, "--nproc-per-node", "2", overrides=("iterations=30", *dotted)
    )
    training(log_dir / "heartbeat", 1)
    agent = torchrun_pid(proc.pid)  # every process of the run is below the supervisor: the warm pool and its forks too
    command_lines = {pid: procfs.read(pid, "cmdline") for pid in procfs.descendants(proc.pid)}
    assert finish(proc, timeout=300) == 0, console.read_text()[-3000:]  # exit 0: trained to the end
    # ps shows each worker and its stand-in by its title (ftrain/proctitle.py) once it has started, no arguments
    titles = sorted(line.rstrip(b"\0") for pid, line in command_lines.items() if line.startswith(b"ftrain: rank "))
    ranks = [b"ftrain: rank 0/2 stand-in", b"ftrain: rank 0/2 worker (run smoke)"]
    assert titles == [*ranks, *(title.replace(b"0/2", b"1/2") for title in ranks)], titles
    assert agent in command_lines
    for pid, line in command_lines.items():
        for secret in secrets:
            assert secret.encode() not in line, f"process {pid}'s command line shows a credential: {line!r}"


def test_a_storage_down_at_start_is_waited_for_without_a_credential_and_sigterm_ends_it_with_143(tmp_path) -> None:
    """The storage-wait path: the supervisor waits for an S3 endpoint that refuses connections, which it never
    reached (one line says so); its lines and its records name the storage without the credentials of its URL. A
    SIGTERM then (a job preempted during the outage) ends it as a preemption: exit 143, one line, a summary, no
    traceback."""
    secrets = ("AKIAHIDDENKEY77", "S3CR3TVALUE99")
    url = f"s3://{secrets[0]}:{secrets[1]}@nobucket/run"
    env = child_env({"AWS_ENDPOINT_URL": f"http://127.0.0.1:{free_port()}"})  # nothing listens there
    console = tmp_path / "console"
    with console.open("wb") as output:
        command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "1", SMOKE, "--storage", url]
        proc = launch([*command, "iterations=2"], cwd=tmp_path, env=env, stdout=output, stderr=subprocess.STDOUT)
    log_dir = tmp_path / "runs" / "smoke" / "s3" / "nobucket" / "run"  # the default for a remote storage
    wait_for(lambda: "has not answered" in console.read_text(), "the storage-wait line", timeout=120)
    proc.send_signal(signal.SIGTERM)
    assert finish(proc, timeout=60) == EXIT_PREEMPTED
    printed = console.read_text()
    assert "Traceback" not in printed and "stopped by a signal" in printed, printed
    # never reached since the command started: one line says so, with a wait of minutes, not an hour
    (line,) = [line for line in printed.splitlines() if "s3://nobucket/run" in line]
    assert "storage s3://nobucket/run has not answered since this command started" in line, printed
    assert "check its URL and endpoint; waiting up to 300 s (--storage-wait)" in line, printed
    recorded = [event["event"] for event in events(log_dir)]
    assert recorded[0] == "storage_wait" and recorded[-2:] == ["preempted", "summary"], recorded
    files = [path for path in tmp_path.rglob("*") if path.is_file()]
    assert log_dir / "events.jsonl" in files
    for path in files:
        for secret in secrets:
            assert secret.encode() not in path.read_bytes(), f"a credential leaked into {path.relative_to(tmp_path)}"
