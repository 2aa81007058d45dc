"""What a person sees on the console: bad input is one line, once; a crash under ``ftrain supervise`` is one cause
line (and an ``events.jsonl`` record), never a traceback wall from torchrun or the workers."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

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
    run_train,
    train_command,
    training,
)

pytestmark = pytest.mark.slow

REFUSAL = "has env.num_envs=4 per rank, the config has 3: set env.num_envs=4"


def supervise(storage: Path, *overrides: str, ranks: int = 2) -> tuple[subprocess.Popen, Path]:
    """``ftrain supervise`` of the smoke config; its stdout and stderr together go to the returned file."""
    command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", str(ranks), "--backoff-initial", "0.2"]
    console = Path(f"{storage}.console")
    with console.open("wb") as output:
        proc = launch(
            [*command, SMOKE, "--storage", str(storage), *overrides],
            cwd=REPO,
            env=child_env({"PYTHONPATH": str(TESTS)}),
            stdout=output,
            stderr=subprocess.STDOUT,
        )
    return proc, console


def test_plain_torchrun_says_bad_input_once_from_rank_0(tmp_path) -> None:
    storage = tmp_path / "run"
    run_train(storage, "iterations=2")
    result = subprocess.run(
        train_command(storage, "env.num_envs=3", ranks=2),
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode != 0
    lines = [line for line in (result.stdout + result.stderr).splitlines() if line.startswith("ftrain: error:")]
    assert len(lines) == 1, result.stderr
    assert REFUSAL in lines[0]


def test_supervised_bad_input_is_one_line_once_and_not_restarted(tmp_path) -> None:
    storage = tmp_path / "run"
    run_train(storage, "iterations=2", ranks=2, supervised=True)
    proc, console = supervise(storage, "env.num_envs=3")
    assert finish(proc) == 2
    text = console.read_text()
    refusal = REFUSAL
    # both ranks refuse; whichever exits 2 first is named (under load torchrun may SIGTERM rank 0 before it exits)
    named = [line for line in text.splitlines() if refusal in line]
    assert len(named) == 1, text
    assert re.fullmatch(
        rf"ftrain supervise: rank [01] refused its input: checkpoint step 2 {re.escape(refusal)}; not restarting",
        named[0],
    ), text
    assert "Traceback" not in text and "ChildFailedError" not in text, text
    usage = [event for event in events(storage) if event["event"] == "exit"][-1]  # the first run's came before
    assert refusal in usage["cause"] and 2 in usage["failures"].values()


def test_supervised_crashes_are_one_cause_line_each(tmp_path) -> None:
    """A worker raising (rank 1, after iteration 3) and a worker killed (rank 0, later): two restarts, two lines."""
    storage = tmp_path / "run"
    crash = hooks_override(probe_hook("CrashingHook", path=tmp_path / "crashed", rank=1, iteration=3))
    proc, console = supervise(storage, "iterations=12", "log.console=true", crash)
    victim = training(storage / "heartbeat", 6, [0])[0]
    os.kill(victim.pid, signal.SIGKILL)
    assert finish(proc, timeout=300) == 0
    text = console.read_text()
    assert "Traceback" not in text and "FAILED" not in text and "settotalmass" not in text, text
    lines = text.splitlines()
    assert any(
        line.startswith(
            "ftrain supervise: attempt 0: rank 1 exited with code 1: RuntimeError: probe crash after iteration 3"
        )
        for line in lines
    ), text
    assert "ftrain supervise: attempt 1: rank 0 killed by SIGKILL" in lines, text
    exits = [event for event in events(storage) if event["event"] == "exit"]
    assert exits[0]["cause"].startswith("rank 1 exited with code 1: RuntimeError: probe crash after iteration 3")
    where = exits[0]["cause"].split(" (traceback in ")[1].rstrip(")")  # the attempt's stderr.log, which holds it
    assert "Traceback" in Path(where).read_text() and "probe crash after iteration 3" in Path(where).read_text()
    assert exits[1]["cause"] == "rank 0 killed by SIGKILL"
    assert events(storage)[-1]["restarts"] == 2


def test_verbose_says_every_save_and_quiet_says_nothing_per_iteration(tmp_path) -> None:
    """The default says the saves at milestones (``tests/train/test_eta.py``); ``-v`` every one; ``-q`` neither
    iterations nor saves, only what went wrong and where the run ended. Every step is kept, so that what is stored is
    what was saved: a save due while two are in flight is left to the next iteration (on a loaded machine, 4 and 5 of
    8 once), and is no save to say."""
    said = {}
    for flag in ("-v", "-q"):
        command = [sys.executable, "-m", "ftrain", "train", flag, SMOKE, "--storage", str(tmp_path / flag)]
        result = subprocess.run(
            [*command, "iterations=8", "checkpoint.interval=1", "checkpoint.keep_last=8"],
            cwd=REPO,
            env=child_env(),
            capture_output=True,
            text=True,
            timeout=300,
        )
        assert result.returncode == 0, result.stderr[-3000:]
        said[flag] = result.stdout.splitlines()
    saves = [line for line in said["-v"] if line.startswith("[ftrain] saved step ")]
    stored = sorted(
        int(step.parent.name.split("-")[1]) for step in (tmp_path / "-v").glob("checkpoints/*/MANIFEST.json")
    )
    assert [int(line.split()[3]) for line in saves] == stored, said["-v"]
    assert stored[0] == 1 and stored[-1] == 8, stored  # the first save is waited for, the last holds
    assert [line for line in said["-v"] if line.startswith("it ")][-1].startswith("it 8/8 | ")
    assert not [line for line in said["-q"] if line.startswith(("it ", "[ftrain] saved step"))], said["-q"]
    storage = tmp_path / "-q"  # where the run ended, said whatever the flag (docs/logging.md)
    assert said["-q"][-2:] == [
        f"[ftrain] run saved in {storage}: newest step 8; logs in {storage}",
        f"[ftrain] play it: ftrain play {storage}   export it: ftrain export {storage} --format onnx",
    ], said["-q"]
