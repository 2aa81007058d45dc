"""Student-teacher distillation with rsl-rl's Distillation: a real teacher checkpoint, 2 real ranks."""

from __future__ import annotations

import shutil
import statistics
import subprocess

import pytest

from helpers import REPO, child_env, final_manifest, metrics_by_iteration, run_train, supervise_command, train_command

pytestmark = pytest.mark.slow

DISTILL = str(REPO / "configs" / "distill_halfcheetah.yaml")
SMALL = [
    "env.num_envs=4",
    "env.kwargs={max_episode_steps: 50}",
    "num_steps_per_env=16",
    "policy.hidden_dims=[32,32]",
    "algorithm.gradient_length=16",
    "checkpoint.interval=4",
]


def test_student_learns_from_teacher_and_resumes_exactly(tmp_path) -> None:
    teacher = tmp_path / "teacher"
    run_train(teacher, "iterations=12")
    teacher_manifest = final_manifest(teacher)

    straight = tmp_path / "straight"
    result = run_train(
        straight, f"teacher={teacher}", "iterations=12", *SMALL, ranks=2, config=DISTILL, supervised=True
    )
    source = teacher / "checkpoints" / "step-000000012"
    assert f"teacher: {source} (step 12, state_sha256 {teacher_manifest['state_sha256'][:16]})" in result.stdout
    behavior = {it: float(row["loss/behavior"]) for it, row in metrics_by_iteration(straight).items()}
    first, last = (
        statistics.fmean(behavior[it] for it in (1, 2)),
        statistics.fmean(behavior[it] for it in (9, 10, 11, 12)),
    )
    assert last < 0.6 * first, f"behaviour loss did not fall: {behavior}"  # means: one iteration is noisy
    manifest = final_manifest(straight)
    assert manifest["teacher"]["digest"] == teacher_manifest["state_sha256"]
    assert manifest["teacher"]["step"] == 12

    resumed = tmp_path / "resumed"
    run_train(resumed, f"teacher={teacher}", "iterations=8", *SMALL, ranks=2, config=DISTILL, supervised=True)
    respelt = "teacher=teacher/"  # the same teacher, spelt relative to tmp_path: no config change
    options = {"ranks": 2, "config": DISTILL, "supervised": True, "cwd": tmp_path}
    result = run_train(resumed, respelt, "iterations=12", *SMALL, **options)
    assert "resumed from step 8" in result.stdout and "changed since step" not in result.stdout, result.stdout
    assert final_manifest(resumed)["state_sha256"] == manifest["state_sha256"]

    other = tmp_path / "other-teacher"  # another teacher named at a resume: the run keeps its own, and says which
    run_train(other, "iterations=2")
    result = run_train(resumed, f"teacher={other}", "iterations=13", *SMALL, **options)
    said = [line for line in result.stdout.splitlines() if "teacher" in line]
    assert said == [
        f"[ftrain] teacher={other} is not the teacher this run started with: it keeps that one, from its checkpoint",
        f"[ftrain] teacher: {source} (step 12, state_sha256 {teacher_manifest['state_sha256'][:16]})",
    ], result.stdout
    assert final_manifest(resumed)["teacher"] == manifest["teacher"]

    # the teacher's run gone (its retention deleted the step, or the run was moved): a resume goes on with the
    # teacher its checkpoint holds, bit for bit as where the teacher is still there
    gone = tmp_path / "resumed-gone"
    shutil.copytree(resumed, gone)
    run_train(resumed, f"teacher={teacher}", "iterations=14", *SMALL, **options)
    teacher.rename(tmp_path / "teacher-moved")
    result = run_train(gone, f"teacher={teacher}", "iterations=14", *SMALL, **options)
    said = [line for line in result.stdout.splitlines() if "teacher" in line]
    assert said[0].startswith(f"[ftrain] teacher={teacher}: ") and said[0].endswith(
        "; the run goes on with the teacher its checkpoint holds"
    ), said
    assert final_manifest(gone)["state_sha256"] == final_manifest(resumed)["state_sha256"]
    assert final_manifest(gone)["teacher"] == manifest["teacher"]
    branched = tmp_path / "branched"  # a new storage that starts from the student's step: its teacher is in there
    result = run_train(branched, f"teacher={teacher}", f"resume={gone}", "iterations=15", *SMALL, **options)
    assert "; the run goes on with the teacher its checkpoint holds" in result.stdout, result.stdout
    assert final_manifest(branched)["teacher"] == manifest["teacher"]
    fresh = subprocess.run(  # a student with nothing to resume from has no teacher at all: one line, exit 2
        train_command(tmp_path / "fresh", f"teacher={teacher}", *SMALL, config=DISTILL),
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
    )
    assert fresh.returncode == 2 and fresh.stderr.startswith(f"ftrain: error: teacher={teacher}: "), fresh.stderr


def test_teacher_from_another_environment_is_one_clear_error(tmp_path) -> None:
    teacher = tmp_path / "hopper"
    run_train(teacher, "iterations=2", "env.id=Hopper-v5")
    command = train_command(tmp_path / "student", f"teacher={teacher}", *SMALL, config=DISTILL)
    result = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if line.startswith("ftrain: error:")]
    assert len(errors) == 1 and "Traceback" not in result.stderr
    assert "trained on Hopper-v5 (observations 11, actions 3)" in errors[0]
    assert "student trains on HalfCheetah-v5 (observations 17, actions 6)" in errors[0]

    shard = teacher / "checkpoints" / "step-000000002" / "common.pt"  # a file of a checkpoint, not the checkpoint
    command = train_command(tmp_path / "student", f"teacher={shard}", *SMALL, config=DISTILL)
    result = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and result.stderr == (
        f"ftrain: error: teacher={shard}: {shard} is a file: a teacher is the checkpoint or policy snapshot of a run "
        "(distillation needs its actor's weights): pass that\n"
    ), result.stderr

    missing = tmp_path / "no-such-run"
    for launch in (train_command, supervise_command):  # refused before a worker starts, nothing made
        command = launch(tmp_path / launch.__name__, f"teacher={missing}", *SMALL, config=DISTILL)
        result = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
        said = f"ftrain: error: teacher={missing}: {missing} does not exist: pass a run's storage or a step directory\n"
        assert (result.returncode, result.stdout + result.stderr) == (2, said), result.stdout + result.stderr
        assert not (tmp_path / launch.__name__).exists()
