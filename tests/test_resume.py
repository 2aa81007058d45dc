"""Exact resume: runs killed with SIGKILL from outside (mid-rollout, mid-update, mid-save) and resumed end with the
same learned state and the same per-iteration metrics as an uninterrupted run."""

from __future__ import annotations

import json
import signal
import subprocess

import pytest

from ftrain.heartbeat import ENV_DIR, read_heartbeats

from runs import (
    REPO,
    child_env,
    final_manifest,
    kill_tree,
    manifests,
    metrics_by_iteration,
    run_train,
    start_train,
    train_command,
    wait_for,
)

pytestmark = pytest.mark.slow

KILLS = [("rollout", 2), ("checkpoint", 4), ("update", 7)]
"""(phase, iteration): SIGKILL the whole process tree once rank 0 is in that phase at or after that iteration."""


def kill_during(
    storage, phase: str, iteration: int, overrides: list[str], ranks: int, heartbeats=None, env: dict | None = None
) -> None:
    heartbeats = heartbeats or storage.parent / f"{storage.name}-heartbeat"
    proc = start_train(storage, *overrides, ranks=ranks, env={**(env or {}), ENV_DIR: str(heartbeats)})

    def in_phase() -> bool:
        beat = read_heartbeats(heartbeats).get(0)
        return beat is not None and beat.phase == phase and beat.iteration >= iteration

    try:
        wait_for(in_phase, f"rank 0 in {phase} at iteration {iteration}", interval=0.001)
    finally:
        kill_tree(proc)
    assert proc.returncode == -signal.SIGKILL
    committed = manifests(storage) if "://" not in str(storage) else {}
    assert all(step <= iteration + 1 for step in committed), f"killed too late: {sorted(committed)}"


@pytest.mark.parametrize(
    ("env_id", "ranks"), [("HalfCheetah-v5", 1), ("HalfCheetah-v5", 2), ("Ant-v5", 1), ("Ant-v5", 2)]
)
def test_killed_anywhere_resumes_bit_for_bit(tmp_path, env_id: str, ranks: int) -> None:
    overrides = [f"env.id={env_id}", "iterations=10", "checkpoint.interval=2", "env.num_envs=8", "num_steps_per_env=32"]
    run_train(tmp_path / "reference", *overrides, ranks=ranks)
    reference = final_manifest(tmp_path / "reference")

    run = tmp_path / "run"
    for phase, iteration in KILLS:
        # a synchronous save keeps the checkpoint phase open for the whole write, so the kill lands inside it
        kill_during(run, phase, iteration, [*overrides, "checkpoint.async_save=false"], ranks)
    result = run_train(run, *overrides, ranks=ranks)
    assert "resumed from step 6 " in result.stdout or "resumed from step 8 " in result.stdout

    assert final_manifest(run)["state_sha256"] == reference["state_sha256"]
    assert metrics_by_iteration(run) == metrics_by_iteration(tmp_path / "reference")


def test_async_and_sync_saves_write_the_same_checkpoints(tmp_path) -> None:
    run_train(tmp_path / "async", "checkpoint.async_save=true", "checkpoint.keep_last=10")
    run_train(tmp_path / "sync", "checkpoint.async_save=false", "checkpoint.keep_last=10")
    left, right = manifests(tmp_path / "async"), manifests(tmp_path / "sync")
    assert sorted(left) == sorted(right) == [2, 4, 6, 8]
    for step in left:
        assert left[step]["state_sha256"] == right[step]["state_sha256"]
        assert left[step]["files"]["rank-00000.pt"] == right[step]["files"]["rank-00000.pt"]


def test_resume_refuses_other_world_size_and_config(tmp_path) -> None:
    storage = tmp_path / "run"
    run_train(storage, "iterations=2")
    for overrides, ranks, message in [
        (["iterations=4"], 2, "written by 1 ranks but this run has 2: run with --nproc-per-node=1"),
        (["iterations=4", "env.num_envs=3"], 1, "set env.num_envs=4"),
        (["iterations=4", "algorithm.clip_param=0.1"], 1, "pass allow_config_change=true"),
    ]:
        result = subprocess.run(
            train_command(storage, *overrides, ranks=ranks), cwd=REPO, env=child_env(), capture_output=True, text=True
        )
        assert result.returncode != 0
        assert message in result.stderr
        if ranks == 1:  # under torchrun, torchrun itself reports the failed worker with a traceback
            assert "Traceback" not in result.stderr
    assert sorted(manifests(storage)) == [2], "a refused resume must not touch the checkpoints"
    result = run_train(storage, "iterations=4", "algorithm.clip_param=0.1", "allow_config_change=true")
    assert "resumed from step 2" in result.stdout
    assert json.loads((storage / "checkpoints/step-000000004/MANIFEST.json").read_text())["iteration"] == 4


def test_two_ranks_on_s3_killed_and_resumed(tmp_path, s3_server, s3_env) -> None:
    from conftest import create_bucket

    url = f"s3://{create_bucket(s3_server)}/runs/hc"
    overrides = ["iterations=8", f"log_dir={tmp_path / 'logs'}"]
    run_train(tmp_path / "reference", "iterations=8", ranks=2)
    kill_during(url, "update", 5, overrides, ranks=2, heartbeats=tmp_path / "heartbeat", env=s3_env)
    result = run_train(url, *overrides, ranks=2, env=s3_env)
    assert "resumed from step 4" in result.stdout
    assert s3_server["secret"] not in result.stdout + result.stderr
    assert (tmp_path / "logs" / "config.yaml").exists()
    manifest = json.loads(_read_s3_manifest(url, 8, s3_env))
    assert manifest["state_sha256"] == final_manifest(tmp_path / "reference")["state_sha256"]
    assert s3_server["secret"] not in json.dumps(manifest)


def _read_s3_manifest(url: str, step: int, env: dict) -> str:
    from ftrain.storage import Storage

    options = {
        "endpoint_url": env["AWS_ENDPOINT_URL"],
        "key": env["AWS_ACCESS_KEY_ID"],
        "secret": env["AWS_SECRET_ACCESS_KEY"],
    }
    return Storage.open(url, options).read(f"checkpoints/step-{step:09d}/MANIFEST.json").decode()


def test_failed_saves_are_logged_training_goes_on_and_persistent_failure_stops(tmp_path) -> None:
    storage = tmp_path / "run"
    (storage / "checkpoints").mkdir(parents=True)
    (storage / "checkpoints" / "step-000000004").write_text("a file where the step directory should go")
    result = run_train(storage, "checkpoint.keep_last=10")
    assert "checkpoint step 4 failed (1/3), earlier ones intact" in result.stdout
    assert sorted(manifests(storage)) == [2, 6, 8]

    blocked = tmp_path / "blocked"
    (blocked / "checkpoints").mkdir(parents=True)
    for step in (2, 4, 6):
        (blocked / "checkpoints" / f"step-{step:09d}").write_text("not a directory")
    failed = subprocess.run(
        train_command(blocked), cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=300
    )
    assert failed.returncode != 0
    assert "3 checkpoints in a row failed to save" in failed.stderr
    assert manifests(blocked) == {}
