"""Exact resume: runs killed with SIGKILL from outside (mid-rollout, mid-update, mid-save) and resumed end with the
same learned state and the same per-iteration metrics as an uninterrupted run."""

from __future__ import annotations

import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ftrain.ckpt.format import DIGEST, QUARANTINED
from ftrain.ckpt.schedule import STORAGE_WAIT_ENV
from ftrain.errors import EXIT_STORAGE_DOWN
from ftrain.heartbeat import ENV_DIR, read_heartbeats
from ftrain.tools.plot import plot_run

from helpers import (
    REPO,
    SMOKE,
    TESTS,
    Hold,
    child_env,
    create_bucket,
    events,
    final_manifest,
    flip_byte,
    hooks_override,
    kill_tree,
    manifests,
    metrics_by_iteration,
    probe_hook,
    run_train,
    start_train,
    tensorboard_by_iteration,
    train_command,
    wait_for,
)

pytestmark = pytest.mark.slow

KILLS = [("rollout", 2, True), ("checkpoint", 4, False), ("rollout", 6, True), ("update", 7, True)]
"""(phase, iteration, async save): SIGKILL the whole process tree once rank 0 is in that phase at or after that
iteration. A synchronous save keeps the checkpoint phase open for the whole write, so that kill lands inside it;
the rollout right after an asynchronous save (iteration 6) runs while the background thread writes step 6."""


def kill_during(
    storage, phase: str, iteration: int, overrides: list[str], ranks: int, heartbeats=None, env: dict | None = None
) -> None:
    """SIGKILL the run's whole process tree once rank 0 is in ``phase`` at or after ``iteration``. A window missed
    (the run ended, or committed step 10, before a look found rank 0 there: a busy core) is tried again from a copy
    of the storage as it was, three tries in all; a remote storage is tried once."""
    heartbeats = heartbeats or storage.parent / f"{storage.name}-heartbeat"
    if "://" in str(storage):
        assert _killed_in(storage, phase, iteration, overrides, ranks, heartbeats, env), f"missed {phase} {iteration}"
        return
    before = storage.parent / f"{storage.name}-before"
    if storage.exists():
        shutil.copytree(storage, before, symlinks=True)
    for _ in range(3):
        if _killed_in(storage, phase, iteration, overrides, ranks, heartbeats, env):
            shutil.rmtree(before, ignore_errors=True)
            return
        shutil.rmtree(storage, ignore_errors=True)
        if before.exists():
            shutil.copytree(before, storage, symlinks=True)
    raise AssertionError(f"three runs ended, or committed step 10, before rank 0 was seen in {phase} at {iteration}")


def _killed_in(storage, phase: str, iteration: int, overrides: list[str], ranks: int, heartbeats, env) -> bool:
    """One try of ``kill_during``: whether the kill landed before the run ended and before step 10."""
    shutil.rmtree(heartbeats, ignore_errors=True)  # a killed try's last beat would be seen at once
    proc = start_train(storage, *overrides, ranks=ranks, env={**(env or {}), ENV_DIR: str(heartbeats)})

    def in_phase_or_ended() -> bool:
        beat = read_heartbeats(heartbeats).get(0)
        return (beat is not None and beat.phase == phase and beat.iteration >= iteration) or proc.poll() is not None

    try:
        wait_for(in_phase_or_ended, f"rank 0 in {phase} at iteration {iteration}", interval=0.001)
    finally:
        kill_tree(proc)
    committed = manifests(storage) if "://" not in str(storage) else {}
    return proc.returncode == -signal.SIGKILL and all(step < 10 for step in committed)


@pytest.mark.slow
def test_a_learning_rate_or_seed_let_through_at_a_resume_is_what_the_run_trains_with(tmp_path) -> None:
    """``allow_config_change`` lets through what the checkpoint holds state of: the learning rate (a fixed schedule's,
    or an adaptive one's, which adapts on from there) and the seed (the random streams go on from the new one). Each
    is what the run trains with from the resume, not only what its line says; the same resume twice, the same bits."""
    trained = {}
    for schedule in ("fixed", "adaptive"):
        base = tmp_path / schedule
        run_train(base, "iterations=2", f"algorithm.schedule={schedule}")
        cases = [("same", []), ("rate", ["algorithm.learning_rate=0.0005"]), ("seed", ["seed=7"])]
        for name, changes in cases if schedule == "fixed" else cases[:2]:  # a seed is no matter of the schedule
            for attempt in (1, 2) if name == "seed" else (1,):
                storage = tmp_path / f"{schedule}-{name}-{attempt}"
                shutil.copytree(base, storage)
                overrides = ["iterations=3", f"algorithm.schedule={schedule}", *changes, "allow_config_change=true"]
                result = run_train(storage, *overrides)
                assert ("changed since step 2" in result.stdout) == bool(changes), result.stdout
                rate = float(metrics_by_iteration(storage)[3]["learning_rate"])
                trained[schedule, name, attempt] = final_manifest(storage)["state_sha256"], rate
    assert trained["fixed", "same", 1][1] == 1e-3 and trained["fixed", "rate", 1][1] == 5e-4  # the default: 1e-3
    adapted = trained["adaptive", "rate", 1][1]  # from the new rate, by 1.5 up or down at each of 4 minibatches
    assert any(adapted == pytest.approx(5e-4 * 1.5**power, rel=1e-9) for power in range(-4, 5)), adapted
    digests = {key: digest for key, (digest, _) in trained.items() if key[2] == 1}
    assert len(set(digests.values())) == len(digests), digests  # each change trained other bits than the same resume
    assert trained["fixed", "seed", 2][0] == digests["fixed", "seed", 1]


@pytest.mark.parametrize(
    ("env_id", "ranks"),
    [  # each env's state and each world size in every run; their other two pairings in the opt-in scale lane
        pytest.param("HalfCheetah-v5", 1, marks=pytest.mark.scale),
        ("HalfCheetah-v5", 2),
        ("Ant-v5", 1),
        pytest.param("Ant-v5", 2, marks=pytest.mark.scale),
    ],
)
def test_killed_anywhere_resumes_bit_for_bit(tmp_path, env_id: str, ranks: int) -> None:
    overrides = [f"env.id={env_id}", "iterations=10", "checkpoint.interval=2", "env.num_envs=8", "num_steps_per_env=32"]
    overrides += ["reward.normalize=true", "policy.std_type=log", "algorithm.reshuffle_each_epoch=true"]
    overrides += ["algorithm.schedule=linear", "algorithm.schedule_iterations=12"]  # as the shipped configs train
    overrides += ["policy.final_noise_std=0.2"]  # the noise's ceiling, a function of the iteration, set on resume too
    overrides += ["log.tensorboard=true"]  # each point of the killed runs' iterations once, their redone ones replaced
    said = run_train(tmp_path / "reference", *overrides, ranks=ranks).stdout
    assert said.count("algorithm.schedule_iterations=12 but iterations=10") == 1, said  # rank 0 says it, once
    reference = final_manifest(tmp_path / "reference")

    run = tmp_path / "run"
    for phase, iteration, async_save in KILLS:
        kill_during(run, phase, iteration, [*overrides, f"checkpoint.async_save={str(async_save).lower()}"], ranks)
    result = run_train(run, *overrides, ranks=ranks)
    resumed = re.search(r"resumed from step (\d+) ", result.stdout)
    assert resumed and 0 < int(resumed[1]) < 10, result.stdout  # which step depends on how far the async saves got
    assert "other arithmetic" not in result.stdout, result.stdout  # the same CPU: it continues bit for bit

    assert final_manifest(run)["state_sha256"] == reference["state_sha256"]
    assert metrics_by_iteration(run) == metrics_by_iteration(tmp_path / "reference")
    shown = tensorboard_by_iteration(run)
    assert sorted(shown) == list(range(1, 11)) and shown == tensorboard_by_iteration(tmp_path / "reference")


def test_a_run_started_from_another_runs_step_goes_on_from_its_own_and_refuses_another_history(tmp_path) -> None:
    """``resume=URL`` names where a storage's history starts. Killed before and after its first commit, the same
    command again (what a supervisor's restart runs) goes on from its own newest step, and ends bit for bit where an
    undisturbed run ends; the same URL into a storage that holds another history is refused in one line, untouched, and
    so is an earlier step of a storage into itself, with a line that says its history goes on past that step. The
    same command goes on also once the source has deleted that step (its retention): the storage's own steps are what
    it resumes from."""
    run_train(tmp_path / "source", "iterations=4")
    start = f"resume={tmp_path / 'source' / 'checkpoints' / 'step-000000004'}"
    overrides = ["iterations=10", "checkpoint.interval=2", start]
    run_train(tmp_path / "reference", *overrides)
    run = tmp_path / "run"
    for phase, iteration, async_save in [("rollout", 5, True), ("update", 8, True)]:
        kill_during(run, phase, iteration, [*overrides, f"checkpoint.async_save={str(async_save).lower()}"], ranks=1)
    assert manifests(run), "a kill after the run's first commit"
    origin = tmp_path / "source" / "checkpoints" / "step-000000004"
    origin.rename(origin.with_name("pruned"))  # as the source's retention deletes it
    result = run_train(run, *overrides, supervised=True)
    origin.with_name("pruned").rename(origin)
    assert f"resume={start.removeprefix('resume=')}: the history of {run} goes on from that step" in result.stdout
    assert final_manifest(run)["state_sha256"] == final_manifest(tmp_path / "reference")["state_sha256"]
    assert metrics_by_iteration(run) == metrics_by_iteration(tmp_path / "reference")

    other = tmp_path / "other"  # the source's history up to step 2: not the step the URL names, nor after it
    shutil.copytree(tmp_path / "source", other)
    shutil.rmtree(other / "checkpoints" / "step-000000004")
    checkpoints = lambda: {path: path.read_bytes() for path in (other / "checkpoints").rglob("*") if path.is_file()}  # noqa: E731
    before = checkpoints()
    command = train_command(other, *overrides)
    refused = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
    assert "already holds checkpoints (newest: step 2) that do not continue " in refused.stderr, refused.stderr
    assert checkpoints() == before

    earlier = f"resume={tmp_path / 'source' / 'checkpoints' / 'step-000000002'}"  # a step of its own history
    command = train_command(tmp_path / "source", "iterations=10", earlier)
    refused = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
    assert "already holds step 2 and goes on past it (newest: step 4)" in refused.stderr, refused.stderr


def test_async_and_sync_saves_write_the_same_checkpoints(tmp_path) -> None:
    run_train(tmp_path / "async", "checkpoint.async_save=true", "checkpoint.keep_last=10")
    run_train(tmp_path / "sync", "checkpoint.async_save=false", "checkpoint.keep_last=10")
    left, right = manifests(tmp_path / "async"), manifests(tmp_path / "sync")
    assert sorted(left) == sorted(right) == [2, 4, 6, 8]
    for step in left:
        assert left[step]["state_sha256"] == right[step]["state_sha256"]
        assert left[step]["files"]["rank-00000.pt"] == right[step]["files"]["rank-00000.pt"]


def test_resume_refuses_other_env_count_config_and_format(tmp_path) -> None:
    storage = tmp_path / "run"
    run_train(storage, "iterations=2")
    described = (storage / "run.json").read_text()
    # one rank each: test_console has the same env-count refusal under plain torchrun at 2 ranks, said once by rank 0
    for overrides, message in [
        (["iterations=4", "env.num_envs=3"], "set env.num_envs=4"),
        (["iterations=4", "env.num_envs=3", "env.id=Hopper-v5"], '(env.id "HalfCheetah-v5" -> "Hopper-v5")'),
        (["iterations=4", "policy.hidden_dims=[32,32]"], "another model than the config asks for (policy.hidden_dims "),
        (["iterations=4", "algorithm.clip_param=0.1"], "pass allow_config_change=true"),
        (["iterations=4", "resume=maybe"], "resume=maybe: maybe does not exist: pass a run's storage"),
    ]:
        result = subprocess.run(
            train_command(storage, *overrides), cwd=REPO, env=child_env(), capture_output=True, text=True
        )
        assert result.returncode == 2 and message in result.stderr and "Traceback" not in result.stderr
    assert sorted(manifests(storage)) == [2], "a refused resume must not touch the checkpoints"
    assert (storage / "run.json").read_text() == described, "nor describe the refused start as the run"
    manifest_file = storage / "checkpoints/step-000000002/MANIFEST.json"
    current = manifest_file.read_text()
    for written, message in [(1, b"holds training state in format 1"), (3, b"in ftrain 0.1's packed format")]:
        older = {key: value for key, value in json.loads(current).items() if key != DIGEST}  # an older ftrain's
        manifest_file.write_text(json.dumps({**older, "state_format": written}))
        result = subprocess.run(train_command(storage, "iterations=4"), cwd=REPO, env=child_env(), capture_output=True)
        assert result.returncode == 2 and message in result.stderr
        assert not (storage / "checkpoints/step-000000002" / QUARANTINED).exists(), "refused, not quarantined"
    bare = {key: value for key, value in json.loads(current).items() if key not in (DIGEST, "state_format", "versions")}
    manifest_file.write_text(json.dumps(bare))  # made by hand or by another tool: no traceback either
    result = subprocess.run(train_command(storage, "iterations=4"), cwd=REPO, env=child_env(), capture_output=True)
    assert result.returncode == 2 and b"wrote it (its versions are not recorded)" in result.stderr, result.stderr
    manifest_file.write_text(current)
    changed = "algorithm.clip_param 0.2 -> 0.1; algorithm.gamma 0.99 -> 0.98"
    refused = subprocess.run(
        train_command(storage, "iterations=4", "algorithm.clip_param=0.1", "algorithm.gamma=0.98"),
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
    )
    assert refused.returncode == 2 and f"trained with a different config ({changed}): restore" in refused.stderr
    allowed = ["iterations=4", "algorithm.clip_param=0.1", "algorithm.gamma=0.98", "allow_config_change=true"]
    supervise = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "1", SMOKE, "--storage", str(storage)]
    result = subprocess.run([*supervise, *allowed], cwd=REPO, env=child_env(), capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "resumed from step 2" in result.stdout
    assert f"changed since step 2 (allow_config_change=true): {changed}" in result.stdout  # in one line
    assert json.loads((storage / "checkpoints/step-000000004/MANIFEST.json").read_text())["iteration"] == 4
    with (storage / "metrics.csv").open() as file:
        rows = {row["iteration"]: row for row in csv.DictReader(file)}
    assert (rows["3"]["resumed_from"], rows["3"]["config_change"], rows["4"]["config_change"]) == ("2", changed, "")
    assert [event.get("config_change") for event in events(storage) if event["event"] == "resumed"] == [changed]
    assert plot_run(storage, tmp_path / "curves.png").changes == [2]


def test_a_run_lengthened_goes_on_with_its_learning_rate_falling_to_the_new_end_and_other_horizons_are_refused(
    tmp_path,
) -> None:
    """``iterations=N`` alone sets a linear schedule's horizon to N: a short run lengthened goes on (one line says
    so), at the rate a run of the new length has there; one asked for no more than it has trained trains nothing and
    says so, unless its step comes from elsewhere; a horizon set apart from the length, or a run shortened before its
    end, is a config change."""
    linear = "algorithm.schedule=linear"
    run_train(tmp_path / "run", "iterations=2", linear)
    lengthened = run_train(tmp_path / "run", "iterations=4", linear).stdout
    said = "changed since step 2 (the learning rate follows iterations): algorithm.schedule_iterations 2 -> 4"
    assert said in lengthened, lengthened
    run_train(tmp_path / "alone", "iterations=4", linear)
    rates = [metrics_by_iteration(tmp_path / name)[3]["learning_rate"] for name in ("run", "alone")]
    assert rates[0] == rates[1] and float(rates[0]) > 0, rates
    record = [tmp_path / "run" / name for name in ("checkpoints/step-000000004/MANIFEST.json", "metrics.csv")]
    before = [path.read_bytes() for path in record]
    idle = run_train(tmp_path / "run", "iterations=3", linear).stdout  # the run is at step 4 already
    assert "nothing to train: the run is already at step 4, asked for iterations=3" in idle, idle
    assert "changed since" not in idle, idle  # the horizon that followed iterations=3 trains nothing
    assert [path.read_bytes() for path in record] == before, "a start that trains nothing writes nothing"
    run_train(tmp_path / "unfinished", "iterations=2", linear, "algorithm.schedule_iterations=4")
    cases = (  # a horizon set apart from the length; a run shortened before its end
        ("run", ["iterations=6", "algorithm.schedule_iterations=5"], "4 -> 5"),
        ("unfinished", ["iterations=3"], "4 -> 3, which iterations=3 sets"),
        ("elsewhere", ["iterations=3", f"resume={tmp_path / 'run'}"], "4 -> 3, which iterations=3 sets"),
    )  # a step another storage (or the spool) hands on is written here under this config: no lower length
    for name, overrides, change in cases:
        command = train_command(tmp_path / name, *overrides, linear)
        refused = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True)
        assert refused.returncode == 2, refused.stderr
        said = f"(algorithm.schedule_iterations {change}): restore the config, pass allow_config_change=true, or start"
        assert said in refused.stderr, refused.stderr
    beside = train_command(tmp_path / "run", "iterations=6", "seed=7", linear)  # lengthened with another change
    refused = subprocess.run(beside, cwd=REPO, env=child_env(), capture_output=True, text=True)
    said = "(seed 1 -> 7; and algorithm.schedule_iterations 4 -> 6, which follows iterations=6 and is taken): restore"
    assert refused.returncode == 2 and said in refused.stderr, refused.stderr


def test_two_ranks_on_s3_killed_and_resumed(tmp_path, s3_server, s3_env, reference_state) -> None:
    url = f"s3://{create_bucket(s3_server)}/runs/hc"
    overrides = ["iterations=8", f"log_dir={tmp_path / 'logs'}"]
    kill_during(url, "update", 5, overrides, ranks=2, heartbeats=tmp_path / "heartbeat", env=s3_env)
    result = run_train(url, *overrides, ranks=2, env=s3_env)
    # step 4 if its save had committed when the kill came, step 2 if it was still being written to S3
    assert re.search(r"resumed from step [24] ", result.stdout), result.stdout
    assert s3_server["secret"] not in result.stdout + result.stderr
    assert (tmp_path / "logs" / "config.yaml").exists()
    manifest = json.loads(_read_s3_manifest(url, 8, s3_env))
    assert manifest["state_sha256"] == reference_state(8)
    assert s3_server["secret"] not in json.dumps(manifest)


def test_a_last_step_only_in_the_spool_reaches_the_storage_before_the_run_ends(tmp_path, s3_server, s3_env) -> None:
    """The run's last step was spooled, but its save to S3 never landed (here: deleted): the next start resumes
    from the spool, finds nothing to train, and commits that step to S3 before it calls the run done. A start with
    the spool switched off would have gone on from step 6 and left step 8 behind: refused, with both ways on."""
    from ftrain.ckpt.retention import delete_step
    from ftrain.ckpt.storage import Storage

    url = f"s3://{create_bucket(s3_server)}/run"
    overrides = ["iterations=8", f"log_dir={tmp_path / 'logs'}"]
    run_train(url, *overrides, env=s3_env)
    final = json.loads(_read_s3_manifest(url, 8, s3_env))
    options = {"endpoint_url": s3_env["AWS_ENDPOINT_URL"], "key": s3_server["key"], "secret": s3_server["secret"]}
    delete_step(Storage.open(url, options), 8)
    switched_off = subprocess.run(
        train_command(url, *overrides, "checkpoint.spool=false"), cwd=REPO, env=child_env(s3_env), capture_output=True
    )
    spool = tmp_path / "logs" / "spool"
    said = (
        f"ftrain: error: checkpoint.spool=false passes over step 8 in the spool {spool}, newer than what {url} holds: "
        f"run with checkpoint.spool=true to go on from it, or delete {spool} to go on from its step 6\n"
    ).encode()
    assert (switched_off.returncode, switched_off.stderr[-len(said) :]) == (2, said), switched_off.stderr
    result = run_train(url, *overrides, env=s3_env)
    assert "resumed from step 8 (the spool " in result.stdout and "nothing to train" in result.stdout, result.stdout
    assert json.loads(_read_s3_manifest(url, 8, s3_env))["state_sha256"] == final["state_sha256"]


def test_a_storage_emptied_of_every_step_keeps_the_spool_which_holds_the_only_copy(
    tmp_path, s3_server, s3_env, reference_state
) -> None:
    """The storage lost every step (its objects deleted, its bucket made anew, an S3 server that kept them in memory
    restarted): the spool's steps were the only ones left, and the next start, finding no step, went fresh and
    deleted them. Another run's start is now refused, the spool kept, with the copy that goes on from it; done as
    it says, the run ends on the uninterrupted bits."""
    from ftrain.ckpt.storage import Storage

    url = f"s3://{create_bucket(s3_server)}/run"
    logs = f"log_dir={tmp_path / 'logs'}"
    run_train(url, "iterations=8", logs, ranks=2, env=s3_env)
    options = {"endpoint_url": s3_env["AWS_ENDPOINT_URL"], "key": s3_server["key"], "secret": s3_server["secret"]}
    Storage.open(url, options).delete_tree("checkpoints")
    refused = subprocess.run(
        train_command(url, "iterations=12", logs), cwd=REPO, env=child_env(s3_env), capture_output=True, text=True
    )
    said = re.search(r"but the spool holds step 8 of its history, .* \((\S+)\): to go on from it, copy", refused.stderr)
    assert refused.returncode == 2 and said, refused.stderr
    spooled = Path(said[1])
    assert (spooled / "MANIFEST.json").exists()
    named = subprocess.run(  # resume= into the spool, which the start would have emptied before reading the step
        train_command(url, "iterations=12", logs, f"resume={spooled}"),
        cwd=REPO,
        env=child_env(s3_env),
        capture_output=True,
        text=True,
    )
    said = f"resume={spooled} is in this run's spool, which a start that does not resume from it empties"
    assert named.returncode == 2 and said in named.stderr, named.stderr
    assert (spooled / "MANIFEST.json").exists()
    fs = Storage.open(url, options).fs
    for file in spooled.iterdir():
        fs.put_file(str(file), f"{url.removeprefix('s3://')}/checkpoints/{spooled.name}/{file.name}")
    result = run_train(url, "iterations=12", logs, ranks=2, env=s3_env)
    assert "resumed from step 8 " in result.stdout, result.stdout
    assert json.loads(_read_s3_manifest(url, 12, s3_env))["state_sha256"] == reference_state(12)


def test_resume_url_on_an_emptied_storage_goes_on_from_its_own_spool_and_keeps_another_historys(
    tmp_path, s3_server, s3_env
) -> None:
    """``resume=URL`` on a storage that lost every step: the spool's steps that continue that same ``resume=`` (the
    same run again) are gone on from; those of another history are its only copy, which the start deleted when it
    took ``resume=``'s step: now refused, the spool kept, and a start that empties a spool says which steps it
    deleted."""
    from ftrain.ckpt.storage import Storage
    from ftrain.identity import RUN_ID_ENV

    source = tmp_path / "source"
    run_train(source, "iterations=4")
    url = f"s3://{create_bucket(s3_server)}/run"
    logs = f"log_dir={tmp_path / 'logs'}"
    started = [url, "iterations=8", logs, f"resume={source}/checkpoints/step-000000004"]
    run_train(*started, env=s3_env | {RUN_ID_ENV: "job"})
    final = json.loads(_read_s3_manifest(url, 8, s3_env))["state_sha256"]
    options = {"endpoint_url": s3_env["AWS_ENDPOINT_URL"], "key": s3_server["key"], "secret": s3_server["secret"]}
    Storage.open(url, options).delete_tree("checkpoints")
    again = run_train(*started, env=s3_env | {RUN_ID_ENV: "job"})
    assert "resumed from step 8 (the spool " in again.stdout, again.stdout
    assert json.loads(_read_s3_manifest(url, 8, s3_env))["state_sha256"] == final
    Storage.open(url, options).delete_tree("checkpoints")
    other = [url, "iterations=8", logs, f"resume={source}/checkpoints/step-000000002"]
    refused = subprocess.run(train_command(*other), cwd=REPO, env=child_env(s3_env), capture_output=True, text=True)
    said = f"but the spool holds step 8 of another history of it ({tmp_path / 'logs' / 'spool'}/checkpoints/"
    assert refused.returncode == 2 and said in refused.stderr and "delete the spool" in refused.stderr, refused.stderr
    assert (tmp_path / "logs" / "spool" / "checkpoints" / "step-000000008" / "MANIFEST.json").exists()
    emptied = run_train(url, "iterations=8", logs, "resume=never", env=s3_env)
    assert re.search(r"emptied the spool \S+ \(steps 8, 6\): this start is fresh", emptied.stdout), emptied.stdout


def _read_s3_manifest(url: str, step: int, env: dict) -> str:
    from ftrain.ckpt.storage import Storage

    options = {
        "endpoint_url": env["AWS_ENDPOINT_URL"],
        "key": env["AWS_ACCESS_KEY_ID"],
        "secret": env["AWS_SECRET_ACCESS_KEY"],
    }
    return Storage.open(url, options).read(f"checkpoints/step-{step:09d}/MANIFEST.json").decode()


def test_failed_saves_are_logged_training_goes_on_and_holds_past_the_unsaved_bound(tmp_path) -> None:
    storage = tmp_path / "run"
    (storage / "checkpoints").mkdir(parents=True)
    (storage / "checkpoints" / "step-000000004").write_text("a file where the step directory should go")
    result = run_train(storage, "checkpoint.keep_last=10", "iterations=12")
    assert "checkpoint step 4 not committed, earlier steps intact" in result.stdout
    retried = int(re.search(r"checkpoint step (\d+) committed: saves work again", result.stdout)[1])
    assert retried in (5, 6), "the newest state is retried as soon as the failed save has settled"
    # then the interval (2) goes on. A boundary met while two saves are in flight (a loaded machine) is owed: saved at
    # the first step that finds a slot (tests/ckpt/test_schedule.py has the rule over random busy patterns); so a step
    # off the interval is saved only where a boundary passed since the save before it
    saved = set(manifests(storage))
    assert {2, retried, 12} <= saved <= {2, retried, *range(retried + 1, 13)}, saved
    after = sorted(step for step in saved if step > retried)
    for before, step in zip([retried, *after], after, strict=False):
        assert step % 2 == 0 or any(b % 2 == 0 for b in range(before + 1, step)), (step, saved)
    blocked = tmp_path / "blocked"
    (blocked / "checkpoints").mkdir(parents=True)
    for step in range(1, 13):  # every step of the run (a file named checkpoints is refused at the start)
        (blocked / "checkpoints" / f"step-{step:09d}").write_text("no step directory can go below a file")
    failed = subprocess.run(
        train_command(blocked, "checkpoint.max_unsaved=3", f"log_dir={tmp_path / 'logs'}"),
        cwd=REPO,
        env=child_env({STORAGE_WAIT_ENV: "3"}),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert failed.returncode == EXIT_STORAGE_DOWN, failed.stderr
    held = re.search(r"training held at step (\d+): (\d+) iterations.* \((rank 0: .*)\); next try", failed.stdout)
    assert held and held[1] == held[2], failed.stdout  # nothing ever saved: every iteration unsaved
    said = (
        rf"{re.escape(str(blocked / 'checkpoints'))}/step-\d{{9}} is a file where ftrain needs a directory: move it out"
    )
    assert re.search(said, held[3]), "the hold says why, and the fix"
    # past the bound of 3 at step 4; at 5 where a save's failure is learned an iteration later (saves run in the
    # background: a loaded machine)
    assert int(held[1]) in (4, 5), failed.stdout
    assert f"held at step {int(held[1]) + 1}" not in failed.stdout, "training stays where it is while it holds"
    assert "took no checkpoint for" in failed.stderr and "Traceback" not in failed.stderr
    assert {path.read_text() for path in (blocked / "checkpoints").iterdir()} == {
        "no step directory can go below a file"
    }


def test_retention_across_a_resume_cleans_abandoned_and_failed_steps(tmp_path) -> None:
    """Retention works from what the run knows (one scan at start, then its own saves): steps found at start,
    an abandoned directory older than the resume point, and a save of this run that failed are all handled."""
    storage = tmp_path / "run"
    keep = ("checkpoint.keep_last=2", "checkpoint.keep_best=0", "checkpoint.keep_every=8", "checkpoint.pinned=[2]")
    run_train(storage, "iterations=4", *keep)
    steps = storage / "checkpoints"
    (steps / "step-000000003").mkdir()
    (steps / "step-000000003" / "rank-00000.pt").write_bytes(b"abandoned by a save that was killed")
    (steps / "step-000000006").write_text("a file where the step directory should go")
    # inline saves: the failed save's outcome is known at once, so which steps are saved does not depend on timing
    result = run_train(storage, "iterations=12", "checkpoint.async_save=false", *keep)
    assert "checkpoint step 6 not committed" in result.stdout
    assert sorted(manifests(storage)) == [2, 8, 10, 12]  # pinned, every 8th, the last 2; 4 was found at start
    assert sorted(path.name for path in steps.iterdir()) == [f"step-{s:09d}" for s in (2, 8, 10, 12)]


def test_corrupt_newest_step_is_quarantined_kept_and_skipped(tmp_path) -> None:
    storage = tmp_path / "run"
    run_train(storage, "iterations=6", "checkpoint.keep_last=5")
    flip_byte(storage / "checkpoints/step-000000006/rank-00000.pt")

    result = run_train(storage, "iterations=6", "checkpoint.keep_last=5")
    assert "skipping checkpoint step 6: corrupt, quarantined" in result.stdout
    assert "resumed from step 4" in result.stdout
    assert "checkpoint step 6 (quarantined) moved to" in result.stdout  # set aside intact, never deleted
    assert (storage / "quarantine/step-000000006" / QUARANTINED).exists()
    run_train(tmp_path / "reference", "iterations=6")
    assert final_manifest(storage)["state_sha256"] == final_manifest(tmp_path / "reference")["state_sha256"]

    manifest = storage / "checkpoints/step-000000006/MANIFEST.json"  # damaged where it still reads as JSON
    manifest.write_text(manifest.read_text().replace('"world_size": 1', '"wXrld_size": 1'))
    result = run_train(storage, "iterations=8", "checkpoint.keep_last=5")
    assert "skipping checkpoint step 6: corrupt, quarantined (MANIFEST.json: unusable: its content" in result.stdout
    assert "resumed from step 4" in result.stdout
    run_train(tmp_path / "reference", "iterations=8")
    assert final_manifest(storage)["state_sha256"] == final_manifest(tmp_path / "reference")["state_sha256"]


def test_no_verified_step_but_corrupt_ones_is_refused_not_wiped(tmp_path) -> None:
    storage = tmp_path / "run"
    run_train(storage, "iterations=2")
    (storage / "checkpoints/step-000000002/MANIFEST.json").write_text("{ not json")
    result = subprocess.run(train_command(storage), cwd=REPO, env=child_env(), capture_output=True, text=True)
    assert result.returncode == 2
    assert "no checkpoint in" in result.stderr and "steps [2] are corrupt" in result.stderr
    assert (storage / "checkpoints/step-000000002/rank-00000.pt").exists(), "the evidence must survive"


def test_sigterm_to_one_worker_stops_both_ranks_at_one_boundary_and_the_rerun_continues(
    tmp_path, reference_state
) -> None:
    heartbeats, hold = tmp_path / "heartbeat", Hold(tmp_path, 3)
    env = {ENV_DIR: str(heartbeats), "PYTHONPATH": str(TESTS)}
    proc = start_train(tmp_path / "run", "iterations=8", hold.override, ranks=2, env=env)
    try:
        hold.held()
        os.kill(read_heartbeats(heartbeats)[1].pid, signal.SIGTERM)  # one rank only: the other learns it by agreement
        hold.release()
        assert proc.wait(timeout=120) == 1  # both ranks exit 143; plain torchrun turns any worker's code into 1
    finally:
        if proc.poll() is None:
            kill_tree(proc)
    beats = read_heartbeats(heartbeats)
    assert {b.phase for b in beats.values()} == {"preempted"}
    stopped = {b.iteration for b in beats.values()}
    assert len(stopped) == 1, f"ranks stopped at different iterations: {stopped}"
    (step,) = stopped
    assert 3 <= step < 8 and step in manifests(tmp_path / "run"), "the stop must save the iteration it stopped at"

    result = run_train(tmp_path / "run", "iterations=8", ranks=2)
    assert f"resumed from step {step} " in result.stdout
    assert final_manifest(tmp_path / "run")["state_sha256"] == reference_state(8)


def test_credentials_never_reach_logs_checkpoints_or_policies(tmp_path, s3_server) -> None:
    secret = s3_server["secret"]
    options = (
        f"storage.options={{endpoint_url: '{s3_server['endpoint_url']}', key: {s3_server['key']}, secret: {secret}}}"
    )
    url = f"s3://{create_bucket(s3_server)}/run"
    result = run_train(url, options, "iterations=2", f"log_dir={tmp_path / 'logs'}", "log.tensorboard=true")
    exported = subprocess.run(
        [*train_command(url)[:3], "export", url, "--format", "torchscript", "-o", str(tmp_path / "policy.pt")],
        cwd=REPO,
        env=child_env(
            {
                "AWS_ENDPOINT_URL": s3_server["endpoint_url"],
                "AWS_ACCESS_KEY_ID": s3_server["key"],
                "AWS_SECRET_ACCESS_KEY": secret,
            }
        ),
        capture_output=True,
        text=True,
    )
    assert exported.returncode == 0, exported.stderr
    assert secret not in result.stdout + result.stderr + exported.stdout + exported.stderr
    for path in [*tmp_path.rglob("*")]:
        if path.is_file():
            assert secret.encode() not in path.read_bytes(), f"credentials leaked into {path}"
    manifest = _read_s3_manifest(
        url,
        2,
        {
            "AWS_ENDPOINT_URL": s3_server["endpoint_url"],
            "AWS_ACCESS_KEY_ID": s3_server["key"],
            "AWS_SECRET_ACCESS_KEY": secret,
        },
    )
    assert secret not in manifest and '"secret": "***"' in manifest


def test_a_failed_final_save_holds_and_a_stop_ends_the_hold_as_an_error_not_success(tmp_path) -> None:
    """The last save cannot commit: training holds (the storage wait is an hour), and SIGTERM ends the hold at once
    with one line and exit 7, not 0."""
    storage = tmp_path / "run"
    (storage / "checkpoints").mkdir(parents=True)
    (storage / "checkpoints" / "step-000000008").write_text("a file where the final step directory should go")
    command = train_command(storage, "log.console=true")
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    proc = subprocess.Popen(command, cwd=REPO, env=child_env(), **pipes)
    for line in proc.stdout:
        if "training held at step 8" in line:
            break
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_STORAGE_DOWN
    errors = [line for line in stderr.splitlines() if line.startswith("ftrain: error:")]
    assert len(errors) == 1 and "took no checkpoint for" in errors[0] and "newest committed step is 6" in errors[0]
    assert "), then a stop came; " in errors[0] and errors[0].endswith(
        "once it takes writes again (it answers, has room, lets this run write)"
    ), errors[0]
    assert "Traceback" not in stderr


@pytest.mark.parametrize(
    ("hook", "said"),
    [
        (
            probe_hook("NumpyStateHook", path="unused"),
            "NumpyStateHook: its state_dict() holds what a checkpoint cannot keep as data (best, of type float64): "
            "keep tensors",
        ),  # saves, never loads
        (
            probe_hook("UnpicklableStateHook", kind="lambda"),
            "UnpicklableStateHook: its state_dict() holds what a checkpoint cannot keep as data (kept, of type "
            "function)",
        ),
        (
            probe_hook("UnpicklableStateHook", kind="lock", after=2),
            "(in ftrain/hooks/probe_hooks.UnpicklableStateHook#0/kept, of type lock): hooks and metrics must keep "
            "plain data",
        ),  # plain at the start: the first save's line
    ],
    ids=["numpy", "lambda", "lock-later"],
)
def test_state_that_would_not_load_back_is_refused_before_training_or_at_its_first_save(tmp_path, hook, said):
    """A hook's state that is not plain data is bad input (exit 2: a supervisor does not restart what would save
    alike), in one line that names the hook, and nothing is committed: before the first iteration (found at the
    first save, it threw away the iterations before it), or at the first save for state that turns bad later. State
    that does not even pickle was a save failure like a storage's, retried and held for up to an hour."""
    env = child_env({"PYTHONPATH": str(TESTS)})
    command = train_command(tmp_path / "run", hooks_override(hook))
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, result.stderr[-2000:]
    errors = [line for line in result.stderr.splitlines() if line.startswith("ftrain: error:")]
    assert len(errors) == 1 and said in errors[0], result.stderr
    assert manifests(tmp_path / "run") == {}


def test_a_step_that_verifies_but_does_not_fit_the_code_is_an_error_and_stays_untouched(tmp_path) -> None:
    """A user's hook whose load_state_dict raises (or a changed model, an rsl-rl upgrade): one line, exit 2, the
    step neither quarantined nor set aside; under the supervisor, no restart either."""
    storage = tmp_path / "run"
    hook = hooks_override(probe_hook("FailingLoadHook"))
    env = {"PYTHONPATH": str(TESTS)}
    run_train(storage, "iterations=4", hook, env=env)
    before = manifests(storage)
    result = subprocess.run(
        train_command(storage, "iterations=6", hook), cwd=REPO, env=child_env(env), capture_output=True, text=True
    )
    assert result.returncode == 2
    errors = [line for line in result.stderr.splitlines() if line.startswith("ftrain: error:")]
    assert len(errors) == 1 and "does not load into this code" in errors[0] and "hook refuses" in errors[0]
    assert "Traceback" not in result.stderr
    assert manifests(storage) == before
    assert not list(storage.rglob(QUARANTINED)) and not (storage / "quarantine").exists()

    supervise = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "1", SMOKE, "--storage"]
    supervised = subprocess.run(
        [*supervise, str(storage), "iterations=6", "log.console=false", hook],
        cwd=REPO,
        env=child_env(env),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert supervised.returncode == 2, supervised.stderr[-3000:]
    assert "does not load into this code" in supervised.stderr
    assert [event["event"] for event in events(storage) if event["event"] == "restart"] == []
    assert manifests(storage) == before
    assert not list(storage.rglob(QUARANTINED))


def test_storage_failing_at_resume_stops_every_rank_at_once_with_one_line(tmp_path) -> None:
    storage = tmp_path / "run"
    storage.mkdir()
    (storage / "checkpoints").symlink_to("checkpoints")  # listing it fails: a storage that is down
    started = time.monotonic()
    result = subprocess.run(
        train_command(storage, "dist_timeout=400", ranks=2), cwd=REPO, env=child_env(), capture_output=True, text=True
    )
    assert result.returncode != 0
    assert time.monotonic() - started < 200, "the other rank must not wait out dist_timeout"  # a cold start: < 60
    errors = [line for line in result.stderr.splitlines() if line.startswith("ftrain: error:")]
    # the lease (reading the newest step's generation on a storage without a lease record), or the resume, finds it
    failed = ("failed while reading its newest step", "failed while choosing a step")
    assert errors and all(any(why in line for why in failed) for line in errors), result.stderr[-3000:]
