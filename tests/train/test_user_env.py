"""Your own robot: a MujocoEnv subclass with its own MJCF model (an included XML file, a mesh), in a module of the
user's that lives in a temporary directory and is imported from the working directory. It trains at 2 ranks, under
``ftrain supervise`` too, resumes bit for bit after SIGKILL (its Python state through ``ftrain_state``), plays,
exports; an env whose Python state ftrain cannot save is named once; an edited robot is refused; bad input is one
line, exit code 2, and no restart."""

from __future__ import annotations

import functools
import re
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from ftrain.heartbeat import ENV_DIR, read_heartbeats

from helpers import (
    REPO,
    TESTS,
    child_env,
    final_manifest,
    hooks_override,
    kill_tree,
    metrics_by_iteration,
    probe_hook,
    run_train,
    start_train,
    supervise_command,
    train_command,
    wait_for,
)

pytestmark = pytest.mark.slow

MEMORY_ARM = ["env.id=userbot:MemoryArm-v0", "iterations=8", "checkpoint.interval=2"]
"""A target and a counter in Python, saved through ftrain_state(): the resume must restore them to be exact."""
NOTICE = "keeps Python state that ftrain cannot save"
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=1", "-m", "ftrain"]
FTRAIN_SCRIPT = Path(sys.executable).parent / "ftrain"
"""The installed command: unlike ``python -m``, it does not put the working directory on the import path itself."""


@pytest.fixture
def work(tmp_path) -> Path:
    """The user's directory: their module ``userbot`` (and a broken one), outside the repository."""
    shutil.copytree(TESTS / "user_robot", tmp_path / "work")
    return tmp_path / "work"


def ftrain(work: Path, *args: str) -> subprocess.CompletedProcess:
    """The ``ftrain`` command as a user runs it, in their directory."""
    result = subprocess.run(
        [str(FTRAIN_SCRIPT), *args], cwd=work, env=child_env(), capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 0, f"ftrain {' '.join(args)}: {result.returncode}\n{result.stdout}{result.stderr}"
    return result


def test_own_robot_trains_supervised_resumes_bit_for_bit_after_sigkill_plays_and_exports(work, tmp_path) -> None:
    # the uninterrupted run, under the supervisor, evaluating and snapshotting the user's env as it goes
    reference = tmp_path / "reference"
    extras = ["eval.every=4", "eval.episodes=2", "snapshots.every=4", "snapshots.formats=[torchscript]"]
    done = subprocess.run(
        supervise_command(reference, *MEMORY_ARM, *extras), cwd=work, env=child_env(), capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr[-3000:]
    expected = final_manifest(reference)
    assert expected["robot"]["env_class"] == "userbot.envs:MemoryArm"
    assert expected["robot"]["python_state"] == "saved by ftrain_state()"
    assert set(expected["robot"]["mjcf"]) == {"robot.xml", "parts/arm.xml", "meshes/block.obj"}
    assert (reference / "policies" / "step-000000008" / "MANIFEST.json").exists()

    # the same run killed twice (after a rollout, after an update) and resumed, under plain torchrun; a smoke run's
    # phases last milliseconds, which a look every 50 ms missed under load: LingerHook lingers a second there, in a
    # heartbeat phase of its own (run-only)
    run, heartbeats = tmp_path / "run", tmp_path / "heartbeats"
    for point, iteration in (("after_rollout", 3), ("after_update", 5)):
        linger = hooks_override(probe_hook("LingerHook", seconds=1, start=iteration))
        env = {ENV_DIR: str(heartbeats), "PYTHONPATH": str(TESTS)}
        proc = start_train(run, *MEMORY_ARM, linger, ranks=2, env=env, cwd=work)
        try:
            wait_for(functools.partial(_lingering, heartbeats, point, iteration), f"{point} at iteration {iteration}")
        finally:
            kill_tree(proc)
    result = run_train(run, *MEMORY_ARM, ranks=2, cwd=work)
    assert re.search(r"resumed from step [2-6] ", result.stdout), result.stdout
    assert NOTICE not in result.stdout
    assert final_manifest(run)["state_sha256"] == expected["state_sha256"]
    returns = {it: row["mean_return"] for it, row in metrics_by_iteration(run).items()}
    assert returns == {it: row["mean_return"] for it, row in metrics_by_iteration(reference).items()}

    shown = ftrain(work, "ckpt", "show", str(run)).stdout
    assert "robot: userbot.envs:MemoryArm (your own; identity " in shown
    assert re.search(r"meshes/block.obj +sha256 [0-9a-f]{64}", shown), shown
    played = ftrain(work, "play", str(run), "--episodes", "2", "--video", "arm.gif").stdout
    assert "episode 2: return" in played and "(102 frames of" in played  # 2 x (50 steps + 1): smoke.yaml's limit
    assert (work / "arm.gif").stat().st_size > 0
    ftrain(work, "export", str(run), "--format", "torchscript", "-o", "arm.pt")
    assert "mean return over 1 episode:" in ftrain(work, "play", "arm.pt").stdout

    # the robot's code changed since: one more observation; its policies no longer fit, in one line each
    code = work / "userbot" / "envs.py"
    edited = code.read_text().replace("(6,), np.float64)\n        super()", "(7,), np.float64)\n        super()")
    code.write_text(edited.replace("self.data.qvel, self.target])", "self.data.qvel, self.target, [0.0]])"))
    fix = "the env's code, model file or env.kwargs changed since it was trained: use the env it was trained on"
    for policy, why in (
        (str(run), "it takes 6 observations, the env gives 7 (obs_normalizer._mean is [1, 6] in the checkpoint but "),
        ("arm.pt", "it takes 6 observations, the env gives 7"),
    ):
        refused = subprocess.run([str(FTRAIN_SCRIPT), "play", policy], cwd=work, env=child_env(), capture_output=True)
        line = refused.stderr.decode()
        assert refused.returncode == 2 and line.count("\n") == 1 and why in line and line.endswith(f"{fix}\n"), line
        assert "does not fit env.id=userbot:MemoryArm-v0 as it is now: " in line, line


def _lingering(heartbeats: Path, point: str, iteration: int) -> bool:
    beat = read_heartbeats(heartbeats).get(0)
    lingering = beat is not None and beat.hook == f"{point} of probe_hooks.LingerHook"
    return lingering and beat.iteration >= iteration


def _train(work: Path, storage: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        train_command(storage, *overrides), cwd=work, env=child_env(), capture_output=True, text=True, timeout=300
    )


def test_unsaved_python_state_is_said_once_and_an_edited_robot_is_refused(work, tmp_path) -> None:
    storage = tmp_path / "run"
    first = run_train(storage, "env.id=userbot:ForgetfulArm-v0", "iterations=2", cwd=work)
    assert first.stdout.count(NOTICE) == 1, first.stdout
    assert "define ftrain_state() and ftrain_set_state(state)" in first.stdout
    robot = final_manifest(storage)["robot"]
    assert robot["python_state"] == "NOT saved: target"

    for name, edit in (("robot.xml", "\n<!-- a longer arm -->\n"), ("parts/arm.xml", " "), ("meshes/block.obj", "#\n")):
        path = work / "userbot" / name
        original = path.read_text()
        path.write_text(original + edit)
        refused = _train(work, storage, "env.id=userbot:ForgetfulArm-v0", "iterations=4")
        assert refused.returncode == 2, refused.stderr
        line = f"ftrain: error: checkpoint step 2 was trained with another robot: {name} has changed (sha256 "
        assert refused.stderr.startswith(line) and refused.stderr.count("\n") == 1, refused.stderr
        assert "allow_config_change=true" in refused.stderr
        if name != "meshes/block.obj":
            path.write_text(original)
    resumed = run_train(storage, "env.id=userbot:ForgetfulArm-v0", "iterations=4", "allow_config_change=true", cwd=work)
    assert "resumed from step 2" in resumed.stdout
    said = "changed since step 2 (allow_config_change=true): robot: meshes/block.obj has changed (sha256 "
    assert said in resumed.stdout, resumed.stdout
    assert final_manifest(storage)["robot"]["mjcf"]["meshes/block.obj"] != robot["mjcf"]["meshes/block.obj"]


BAD_INPUT = [
    (["env.id=nosuchbot:Arm-v0"], "env.id: module 'nosuchbot' does not import (ModuleNotFoundError: No module named"),
    (
        ["env.id=Broken-v0", "env.imports=[brokenbot]"],
        "env.imports: module 'brokenbot' does not import (NameError: name 'undefined_robot_name' is not defined "
        "(brokenbot.py, line 6))",
    ),
    (["env.id=userbot:Leg-v0"], "registered no environment 'Leg-v0' (they registered Arm-v0, DictArm-v0,"),
    (["env.id=userbot:NotMujoco-v0"], "is a userbot.envs:NotMujoco, not a gymnasium.envs.mujoco.MujocoEnv"),
    (["env.id=userbot:Arm-v0", "env.kwargs={xml_file: missing.xml}"], "userbot/missing.xml does not exist"),
    (
        ["env.id=userbot:Arm-v0", "env.kwargs={xml_file: broken.xml}"],
        "its MuJoCo model userbot/broken.xml does not compile (XML Error: Schema violation: unrecognized attribute: "
        "'stiffnes' Element 'joint', line 5)",
    ),
    (["env.id=userbot:DictArm-v0"], "has the observation space Dict('angles': Box("),
    (  # the smoke config's env.kwargs set one: cleared
        ["env.id=userbot:EndlessArm-v0", "env.kwargs={}"],
        "env.id='userbot:EndlessArm-v0' has no time limit (gymnasium's max_episode_steps, of its registration)",
    ),
    (
        ["env.id=HalfCheetah-v5", "env.kwargs={max_episode_steps: -1}"],  # gymnasium's "no TimeLimit wrapper"
        "env.kwargs max_episode_steps=-1 leaves env.id='HalfCheetah-v5' without a time limit: an episode may never end",
    ),
    (  # taken by the constructor, fails in the reward: a probe's traceback, and a crash loop under the supervisor
        ["env.id=HalfCheetah-v5", "env.kwargs={forward_reward_weight: abc}"],
        "env.id='HalfCheetah-v5' fails on its first reset or step: TypeError: can't multiply sequence by non-int",
    ),
]


def test_bad_input_is_one_line_exit_2_and_nothing_started_or_made_under_supervise_nor_restarted(work, tmp_path) -> None:
    def launch(case: int, supervised: bool) -> tuple[int, bool, subprocess.CompletedProcess]:
        overrides, _ = BAD_INPUT[case]
        storage = tmp_path / f"{'supervised' if supervised else 'torchrun'}-{case}"
        # one rank each: what a rank does with bad input does not depend on the world size, and each rank costs seconds
        command = supervise_command(storage, "iterations=1", *overrides, ranks=1) if supervised else None
        command = command or [*TORCHRUN, *train_command(storage, "iterations=1", *overrides)[3:]]
        result = subprocess.run(command, cwd=work, env=child_env(), capture_output=True, text=True, timeout=300)
        return case, supervised, result

    # the supervisor checks the user's env in a child before it starts anything (about a second): every case; the
    # workers check it again, which plain torchrun relies on: every other case (each is a torchrun and a worker)
    jobs = [(case, True) for case in range(len(BAD_INPUT))] + [(case, False) for case in range(0, len(BAD_INPUT), 2)]
    jobs += [(len(BAD_INPUT) - 1, False)] if len(BAD_INPUT) % 2 == 0 else []  # the first step's check, too
    with ThreadPoolExecutor(max_workers=2) as pool:
        runs = list(pool.map(lambda job: launch(*job), jobs))
    for case, supervised, result in runs:
        message = BAD_INPUT[case][1]
        where = f"{BAD_INPUT[case][0]} {'supervised' if supervised else 'torchrun'}: {result.stderr[-2000:]}"
        if supervised:  # one line, exit 2, and no torchrun, log directory or storage
            assert result.returncode == 2 and result.stderr.count("\n") == 1, where
            assert result.stderr.startswith("ftrain: error: ") and message in result.stderr, where
            assert not (tmp_path / f"supervised-{case}").exists(), where
        else:  # each rank exits 2; rank 0 prints the line, once (torchrun adds its own report of the failed ranks)
            assert result.returncode != 0 and re.search(r"exitcode\s*:\s*2", result.stderr), where
            refusals = [line for line in result.stderr.splitlines() if line.startswith("ftrain: error:")]
            assert len(refusals) == 1 and message in refusals[0], where
            assert not (tmp_path / f"torchrun-{case}").exists(), where  # each rank makes the env before anything


def test_a_student_distils_from_a_teacher_of_ones_own_robot_and_resumes_exactly(work, tmp_path) -> None:
    """Distillation is one more feature every MujocoEnv gets: the teacher and the student train the user's robot."""
    teacher = tmp_path / "teacher"
    run_train(teacher, *MEMORY_ARM, cwd=work)
    distill = [f"teacher={teacher}", "env.id=userbot:MemoryArm-v0", "env.num_envs=4", "num_steps_per_env=16"]
    distill += ["policy.hidden_dims=[32,32]", "algorithm.gradient_length=16", "checkpoint.interval=2"]
    config = str(REPO / "configs" / "distill_halfcheetah.yaml")
    straight = tmp_path / "straight"
    result = run_train(straight, *distill, "iterations=6", ranks=2, config=config, cwd=work, supervised=True)
    assert "teacher: " in result.stdout and "(step 8," in result.stdout
    manifest = final_manifest(straight)
    assert manifest["teacher"]["digest"] == final_manifest(teacher)["state_sha256"]
    assert manifest["robot"]["env_class"] == "userbot.envs:MemoryArm"
    resumed = tmp_path / "resumed"
    run_train(resumed, *distill, "iterations=4", ranks=2, config=config, cwd=work, supervised=True)
    run_train(resumed, *distill, "iterations=6", ranks=2, config=config, cwd=work, supervised=True)
    assert final_manifest(resumed)["state_sha256"] == manifest["state_sha256"]
