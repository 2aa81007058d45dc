"""Shared helpers for tests that run real ``ftrain train`` processes (plain or under torchrun)."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path

from ftrain import procfs
from ftrain.heartbeat import read_heartbeats

REPO = Path(__file__).resolve().parents[1]
SMOKE = str(REPO / "configs" / "smoke.yaml")
TIMING = ("steps_per_s", "collect_time", "learn_time", "iteration_time")
"""Metrics that measure wall-clock time: the only ones allowed to differ between identical runs."""


def train_command(storage: str | Path, *overrides: str, ranks: int = 1, config: str = SMOKE) -> list[str]:
    launcher = [sys.executable, "-m", "ftrain"]
    if ranks > 1:
        launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}"]
        launcher += ["-m", "ftrain"]
    return [*launcher, "train", config, "--storage", str(storage), "log.console=false", *overrides]


def child_env(extra: dict | None = None) -> dict:
    return {**os.environ, "OMP_NUM_THREADS": "1", **(extra or {})}


def run_train(
    storage: str | Path, *overrides: str, ranks: int = 1, config: str = SMOKE, env: dict | None = None
) -> subprocess.CompletedProcess:
    """Run training to completion; fail the test with its output if it does not exit 0."""
    result = subprocess.run(
        train_command(storage, *overrides, ranks=ranks, config=config),
        cwd=REPO,
        env=child_env(env),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, (
        f"training failed ({result.returncode}):\n{result.stdout[-3000:]}{result.stderr[-5000:]}"
    )
    return result


def start_train(
    storage: str | Path, *overrides: str, ranks: int = 1, config: str = SMOKE, env: dict | None = None
) -> subprocess.Popen:
    """Start training in a new session, so a test can kill the whole process tree like a lost machine."""
    return subprocess.Popen(
        train_command(storage, *overrides, ranks=ranks, config=config),
        cwd=REPO,
        env=child_env(env),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


LAUNCHED: list[subprocess.Popen] = []
"""Supervisors the tests started; conftest stops any still running after each test."""


def launch(command: list[str], **popen: object) -> subprocess.Popen:
    """Start a long-lived process (a supervisor) that must not outlive the test that started it."""
    LAUNCHED.append(subprocess.Popen(command, **popen))
    return LAUNCHED[-1]


def stop_launched() -> None:
    """Two SIGTERMs stop a supervisor and its workers at once."""
    while LAUNCHED:
        proc = LAUNCHED.pop()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)


def finish(proc: subprocess.Popen, timeout: float = 180) -> int:
    """The exit code of ``proc``; killed (and the test failed) if it takes longer than ``timeout``."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise


def events(log_dir: str | Path) -> list[dict]:
    """The supervisor's ``events.jsonl`` of a run, one dict per decision."""
    path = Path(log_dir) / "events.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


def torchrun_pid(supervisor_pid: int) -> int:
    """The torchrun agent a supervisor launched (waits until there is one)."""

    def find() -> int | None:
        for pid in procfs.pids():
            fields = procfs.stat_fields(pid)
            if fields and int(fields[1]) == supervisor_pid and b"torch.distributed.run" in procfs.read(pid, "cmdline"):
                return pid
        return None

    return wait_for(find, "torchrun")


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (torchrun starts each worker in a session of its own, so a process group
    kill does not reach them)."""
    children: dict[int, list[int]] = {}
    for child in procfs.pids():
        if fields := procfs.stat_fields(child):
            children.setdefault(int(fields[1]), []).append(child)
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def kill_tree(proc: subprocess.Popen) -> None:
    """SIGKILL a launched process and everything below it at once, like a machine that lost power."""
    for pid in [proc.pid, *descendants(proc.pid)]:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    proc.wait()


def wait_for(predicate, what: str, timeout: float = 120.0, interval: float = 0.005):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def training(heartbeat_dir: str | Path, iteration: int, ranks: Iterable[int] = (0, 1)) -> dict:
    """The heartbeats in ``heartbeat_dir`` once each of ``ranks`` has completed ``iteration`` iterations and trains
    on (in rollout or update)."""
    ranks = list(ranks)

    def ready() -> dict | None:
        beats = read_heartbeats(Path(heartbeat_dir))
        past = [beats.get(rank) for rank in ranks]
        return beats if all(b and b.iteration >= iteration and b.phase in ("rollout", "update") for b in past) else None

    return wait_for(ready, f"ranks {ranks} at iteration {iteration} in {heartbeat_dir}")


def manifests(storage: str | Path) -> dict[int, dict]:
    """Every committed step's manifest in a local storage, by step."""
    found = {}
    for path in Path(storage).glob("checkpoints/step-*/MANIFEST.json"):
        found[int(path.parent.name.removeprefix("step-"))] = json.loads(path.read_text())
    return found


def flip_byte(path: Path) -> None:
    """Damage a file the way bit rot does: one byte in the middle inverted."""
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def final_manifest(storage: str | Path) -> dict:
    steps = manifests(storage)
    assert steps, f"no committed checkpoint in {storage}"
    return steps[max(steps)]


def metrics_by_iteration(log_dir: str | Path) -> dict[int, dict[str, str]]:
    """``metrics.csv`` rows by iteration, the last row winning (a resumed run redoes some iterations)."""
    with (Path(log_dir) / "metrics.csv").open() as file:
        rows = {int(row["iteration"]): row for row in csv.DictReader(file)}
    return {it: {k: v for k, v in row.items() if k not in TIMING} for it, row in rows.items()}
