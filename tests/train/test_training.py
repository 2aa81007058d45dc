"""Multi-process training for real: torchrun, gloo, MuJoCo, rsl-rl's PPO."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import pytest
import yaml

from ftrain.train.phases import PHASES

from helpers import (
    SMOKE,
    TESTS,
    child_env,
    final_manifest,
    hooks_override,
    metrics_by_iteration,
    probe_hook,
    run_train,
    train_command,
)

PROBES = {"PYTHONPATH": str(TESTS)}


def hook(target: str, path) -> str:
    return hooks_override(probe_hook(target, path=path))


@pytest.mark.slow
def test_ranks_agree_after_every_iteration_and_the_seed_decides(tmp_path, reference_run) -> None:
    agreement = tmp_path / "agreement.jsonl"
    run_train(tmp_path / "a", hook("RankAgreementHook", agreement), ranks=2, env=PROBES, supervised=True)
    lines = [json.loads(line) for line in agreement.read_text().splitlines()]
    assert [line["iteration"] for line in lines] == list(range(1, 9))
    for line in lines:
        assert len(line["digests"]) == 2
        assert line["digests"][0] == line["digests"][1], f"ranks diverged at iteration {line['iteration']}"
    assert len({line["digests"][0] for line in lines}) == 8, "the learned state must change every iteration"

    run_train(tmp_path / "c", "seed=2", ranks=2, supervised=True)
    same, other = final_manifest(reference_run(8)), final_manifest(tmp_path / "c")
    assert final_manifest(tmp_path / "a")["state_sha256"] == same["state_sha256"]
    assert other["state_sha256"] != same["state_sha256"]
    assert metrics_by_iteration(tmp_path / "a") == metrics_by_iteration(reference_run(8))


@pytest.mark.slow
def test_a_runs_config_yaml_continues_it_from_any_directory(tmp_path) -> None:
    """The saved ``config.yaml`` names the run's local paths absolute: a storage typed relative (``./run//``) named
    another directory from elsewhere, where ``ftrain train <run>/config.yaml`` started a fresh run instead."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    train = [sys.executable, "-m", "ftrain", "train"]
    for config, cwd, iterations in ((SMOKE, tmp_path, 2), (str(tmp_path / "run" / "config.yaml"), elsewhere, 4)):
        storage = ["--storage", "./run//"] if cwd == tmp_path else []
        command = [*train, config, *storage, f"iterations={iterations}", "log.console=false"]
        done = subprocess.run(command, cwd=cwd, env=child_env(), capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
    assert "resumed from step 2" in done.stdout, done.stdout
    saved = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert saved["storage"]["url"] == saved["log_dir"] == str(tmp_path / "run") and saved["iterations"] == 4
    assert final_manifest(tmp_path / "run")["step"] == 4 and not any(elsewhere.iterdir())
    # moved, then moved again and supervised (whose workers read the file after the supervisor has claimed the new
    # place): each goes on where it lies, where its logs were written back to the old place
    moved, again = tmp_path / "moved", tmp_path / "again"
    (tmp_path / "run").rename(moved)
    for run, iterations, command in ((moved, 6, ["train"]), (again, 8, ["supervise", "--nproc-per-node", "1"])):
        if run == again:
            moved.rename(again)
        words = [sys.executable, "-m", "ftrain", *command, str(run / "config.yaml"), f"iterations={iterations}"]
        words.append("log.console=false")
        done = subprocess.run(words, cwd=elsewhere, env=child_env(), capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stdout + done.stderr
        assert final_manifest(run)["step"] == iterations and max(metrics_by_iteration(run)) == iterations
    assert not (tmp_path / "run").exists() and not moved.exists() and not any(elsewhere.iterdir())


@pytest.mark.slow
def test_single_process_and_outputs(tmp_path) -> None:
    """Started elsewhere than in the repository, to see that MuJoCo neither prints its warnings (HalfCheetah's model
    uses a deprecated attribute: a warning and a blank line per environment) nor appends them to a MUJOCO_LOG.TXT in
    the working directory."""
    result = run_train(tmp_path / "run", "log.console=true", "log.tensorboard=true", "eval.every=4", cwd=tmp_path)
    assert "settotalmass" not in result.stdout + result.stderr and "\n\n" not in result.stdout
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    lines = [line for line in result.stdout.splitlines() if line.startswith("it ")]
    assert len(lines) == 8 and lines[-1].startswith("it 8/8 |")
    for field in ("steps/s", "return", "len", "eval", "value", "surrogate", "entropy", "lr", "ETA"):
        assert field in lines[-1]
    assert [" | eval " in line for line in lines] == [False, False, False, True] * 2
    run = tmp_path / "run"
    assert "HalfCheetah-v5" in (run / "config.yaml").read_text()
    assert sorted(metrics_by_iteration(run)) == list(range(1, 9))
    assert list((run / "tensorboard").glob("events.out.tfevents.*"))

    records = lambda: {path: path.read_bytes() for path in run.glob("*.*") if path.suffix != ".lock"}  # noqa: E731
    kept = records()
    command = train_command(tmp_path / "other", f"log_dir={run}")  # another storage's run told to log here, later
    other = subprocess.run(command, cwd=tmp_path, env=child_env(), capture_output=True, text=True)
    assert other.returncode == 2 and other.stderr.count("\n") == 1, other.stderr
    assert f"log directory {run} holds the records of the run on {run} " in other.stderr, other.stderr
    assert records() == kept and kept[run / "storage.txt"] == f"{run}\n".encode()
    assert not (tmp_path / "other" / "checkpoints").exists()

    logs = tmp_path / "refused-logs"  # a run refused before it trained (a changed config) leaves its log_dir anyone's
    changed = subprocess.run(train_command(run, "seed=3", f"log_dir={logs}"), env=child_env(), capture_output=True)
    assert changed.returncode == 2 and b"different config" in changed.stderr, changed.stderr
    third = subprocess.run(train_command(tmp_path / "third", "iterations=1", f"log_dir={logs}"), env=child_env())
    assert third.returncode == 0 and (logs / "storage.txt").read_text() == f"{tmp_path / 'third'}\n"


@pytest.mark.slow
def test_hook_state_survives_resume(tmp_path) -> None:
    counter = tmp_path / "count.json"
    run_train(tmp_path / "run", hook("CountingHook", counter), "iterations=4", env=PROBES)
    assert json.loads(counter.read_text()) == {"iteration": 4, "seen": 4}
    result = run_train(tmp_path / "run", hook("CountingHook", counter), "iterations=7", env=PROBES)
    assert "resumed from step 4" in result.stdout
    assert json.loads(counter.read_text()) == {"iteration": 7, "seen": 7}


LEARNING_ADDITIONS = [
    "reward.normalize=true",
    "algorithm.schedule=linear",
    "algorithm.schedule_iterations=60",
    "algorithm.reshuffle_each_epoch=true",
    "policy.obs_clip=10",
    "policy.std_type=log",
]
"""What ftrain adds to rsl-rl's PPO for learning (issue #13), all at once as the shipped configs use them."""


@pytest.mark.slow
@pytest.mark.parametrize("additions", [[], [*LEARNING_ADDITIONS, "seed=3"]], ids=["rsl-rl", "additions"])
def test_it_learns_inverted_pendulum_with_two_ranks(tmp_path, additions: list[str]) -> None:
    """An untrained policy balances for ~5-15 steps; measured here: ~200 after 60 iterations, first ones < 20. Not on
    every seed: with the additions, seeds 1-7 reached 70, 156, 215, 210, 218, 210 and 233 (session 28; the code before
    the world-size change: 225, 236, 223, 238, 98, 220 and 83), so this case runs seed 3 (issue "A policy on every
    seed")."""
    run_train(
        tmp_path / "run",
        "env.id=InvertedPendulum-v5",
        "env.kwargs={}",
        "env.num_envs=16",
        "num_steps_per_env=32",
        "iterations=60",
        "policy.hidden_dims=[64,64]",
        "algorithm.num_learning_epochs=5",
        "algorithm.num_mini_batches=4",
        "checkpoint.interval=100",
        *additions,
        ranks=2,
        supervised=True,
    )
    metrics = metrics_by_iteration(tmp_path / "run")
    first = float(metrics[2]["mean_return"])
    last = float(metrics[60]["mean_return"])
    assert first < 30, f"an untrained policy should fall quickly, got {first}"
    assert last > 100, f"PPO did not learn to balance: mean return {last} after 60 iterations"
    with (tmp_path / "run" / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    for row in rows[1:]:  # where each iteration's time went (mean over the 2 ranks): it adds up to the iteration's
        phases = {name: float(row[f"time/{name}_ms"]) for name in PHASES}
        slowest = {name: float(row[f"time/{name}_max_ms"]) for name in PHASES}
        # the slowest rank's: at least the mean, and what it leaves the other rank is a time too
        assert all(phases[name] <= slowest[name] <= 2 * phases[name] + 1e-6 for name in PHASES), row
        assert min(phases.values()) >= 0 and sum(phases.values()) >= 0.8 * 1000 * float(row["iteration_time"]), row
        assert phases["env"] > 0 and phases["update"] > 0 and phases["sync_update"] > 0 and phases["sync_metrics"] > 0
    assert all(float(row["time/sync_rewards_ms"]) > 0 for row in rows) == bool(additions)  # reward normalisation


@pytest.mark.slow
@pytest.mark.parametrize(
    "damage, after",
    [
        (lambda data: data + b"\0" * 200, [1, 2, 3, 4, 5, 6]),  # a power loss's NUL tail: every row stays
        (lambda data: data[: data.rindex(b"\n", 0, -1) + 8], [1, 2, 3, 5, 6]),  # the last row cut short: it goes
        (lambda data: data.replace(b"\n3,", b"\n3,\xff", 1), [1, 2, 4, 5, 6]),  # bytes that are not text: row dropped
        (lambda data: data.replace(b"\n2,", "\n\u00b2,".encode(), 1), [1, 3, 4, 5, 6]),  # "²": a digit to isdigit
        (lambda data: b"hello world\n1\n", [5, 6]),  # not a metrics CSV: set aside for a new one
    ],
    ids=["nul-tail", "cut-row", "not-text", "not-a-number", "not-metrics"],
)
def test_a_damaged_metrics_csv_never_stops_a_resume(tmp_path, damage, after) -> None:
    """The run resumes from step 4 (of 6) whatever became of its metrics.csv, and keeps every row that is whole."""
    run = tmp_path / "run"
    run_train(run, "iterations=4")
    damaged = damage((run / "metrics.csv").read_bytes())
    (run / "metrics.csv").write_bytes(damaged)
    resumed = run_train(run, "iterations=6")
    assert sorted(metrics_by_iteration(run)) == after
    assert all(None not in row.values() for row in csv.DictReader((run / "metrics.csv").open(newline="")))
    if after == [5, 6]:
        assert "set aside as metrics.csv.unreadable" in resumed.stdout + resumed.stderr
        assert (run / "metrics.csv.unreadable").read_bytes() == damaged
