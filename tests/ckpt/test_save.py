"""The save path: snapshots training cannot change, a digest of the learned state that only its values decide,
stop saves that commit when every process gets SIGTERM, and no process besides the ranks."""

from __future__ import annotations

import os
import random
import re
import shutil
import signal
import subprocess
import threading
import uuid

import pytest
import torch

from ftrain import procfs
from ftrain.ckpt.format import MANIFEST, VERIFIED, decode, encode, learned_state, state_digest, step_dir, verify_step
from ftrain.ckpt.save import Result, StepWriter, snapshot
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.comm.group import RankInfo
from ftrain.config import CheckpointConfig, Config, load_config
from ftrain.heartbeat import ENV_DIR
from ftrain.train.trainer import train

from helpers import (
    REPO,
    SMOKE,
    TESTS,
    Hold,
    StoreProxy,
    assert_same,
    child_env,
    final_manifest,
    finish,
    manifests,
    start_train,
    train_command,
    wait_for,
)

LONG = ("iterations=100000", "checkpoint.interval=2")


def sample_state() -> dict:
    return {
        "actor_state_dict": {"weight": torch.arange(6.0).reshape(2, 3), "bias": torch.ones(2)},
        "optimizer_state_dict": {
            "state": {0: {"step": torch.tensor(3.0), "exp_avg": torch.zeros(2, 3)}},
            "param_groups": [{"lr": 1e-3, "betas": (0.9, 0.999), "params": [0]}],
        },
        "counts": torch.arange(3),
        "name": "HalfCheetah-v5",
    }


def test_a_snapshot_is_a_copy_that_training_cannot_change() -> None:
    state = sample_state()
    copy = snapshot(state)
    assert_same(copy, sample_state())
    state["actor_state_dict"]["weight"].add_(1)  # what the next update does to the live parameters
    state["optimizer_state_dict"]["param_groups"][0]["params"].append(1)
    assert_same(copy, sample_state())


def test_a_snapshot_reuses_the_memory_of_an_earlier_one_of_the_same_layout() -> None:
    earlier = snapshot(sample_state())
    state = sample_state()
    state["actor_state_dict"]["weight"].mul_(3)
    state["counts"] = torch.arange(5)  # another shape: a fresh tensor
    copy = snapshot(state, earlier)
    assert_same(copy, snapshot(state))
    assert copy["actor_state_dict"]["weight"].data_ptr() == earlier["actor_state_dict"]["weight"].data_ptr()
    assert copy["counts"].data_ptr() != earlier["counts"].data_ptr()
    state["actor_state_dict"]["weight"].add_(1)
    assert not torch.equal(copy["actor_state_dict"]["weight"], state["actor_state_dict"]["weight"])


def test_the_digest_is_equal_iff_the_values_are_bitwise_equal() -> None:
    state = sample_state()
    assert state_digest(sample_state()) == state_digest(state)
    assert state_digest(decode(encode(state))) == state_digest(state)  # the file encoding does not count
    reordered = dict(reversed(list(sample_state().items())))
    assert state_digest(reordered) == state_digest(state)  # nor does dict order

    nudged = sample_state()
    bias = nudged["actor_state_dict"]["bias"]
    bias[0] = torch.nextafter(bias[0], torch.tensor(2.0))  # one bit in the last place
    assert state_digest(nudged) != state_digest(state)
    reshaped = sample_state()
    reshaped["counts"] = reshaped["counts"].reshape(3, 1)  # same bytes, another shape
    assert state_digest(reshaped) != state_digest(state)
    retyped = {"x": torch.zeros(2, dtype=torch.int32)}
    assert state_digest(retyped) != state_digest({"x": torch.zeros(2, dtype=torch.float32)})
    renamed = sample_state()
    renamed["optimizer_state_dict"]["param_groups"][0]["lr"] = 2e-3
    assert state_digest(renamed) != state_digest(state)


def test_the_learned_state_is_the_state_dicts_only() -> None:
    state = sample_state()
    other = sample_state() | {"counts": torch.zeros(3), "name": "Ant-v5", "iter": 7}
    assert set(learned_state(state)) == {"actor_state_dict", "optimizer_state_dict"}
    assert state_digest(learned_state(other)) == state_digest(learned_state(state))


@pytest.mark.slow
def test_sigterm_to_every_process_still_commits_the_stop_save_and_ranks_have_no_helpers(tmp_path) -> None:
    storage = tmp_path / "run"
    proc = start_train(storage, *LONG, ranks=2)
    before = max(wait_for(lambda: manifests(storage), "a committed checkpoint"))
    ranks = [pid for pid in procfs.descendants(proc.pid) if int(procfs.stat_fields(pid)[1]) == proc.pid]
    assert len(ranks) == 2
    assert [pid for rank in ranks for pid in procfs.descendants(rank)] == [], "saves run inside the ranks, no helper"
    for pid in ranks:  # what Slurm does to the workers at the end of a job step
        os.kill(pid, signal.SIGTERM)
    assert finish(proc) == 1, "plain torchrun: its workers exit 143 after the stop save, it exits 1"
    newest = max(manifests(storage))
    assert newest >= before
    assert verify_step(Storage.open(str(storage)), newest).ok


def train_here(config: Config) -> None:
    """Train ``config`` to its end in this process (a memory:// storage lives only here), leaving the signal handlers
    as they were."""
    handlers = {number: signal.getsignal(number) for number in (signal.SIGTERM, signal.SIGINT)}
    try:
        assert train(config) == 0
    finally:
        for number, handler in handlers.items():
            signal.signal(number, handler)


@pytest.mark.parametrize("async_save", [True, False])
def test_a_memory_run_saves_and_its_steps_verify(tmp_path, async_save: bool) -> None:
    """memory:// storage lives inside one process: the writer thread shares it, the inline path too."""
    url = f"memory://ftrain-test/{uuid.uuid4().hex}"
    overrides = ["iterations=4", "checkpoint.interval=2", f"log_dir={tmp_path}", "log.console=false"]
    config = load_config(SMOKE, [*overrides, f"checkpoint.async_save={str(async_save).lower()}"], storage=url)
    train_here(config)
    steps = scan(Storage.open(url), full=True)
    assert [(info.step, info.status) for info in steps] == [(4, VERIFIED), (2, VERIFIED)]
    assert steps[0].manifest["iteration"] == 4


@pytest.mark.slow
def test_when_rank_0_cannot_write_a_manifest_every_rank_hears_so_and_training_goes_on_to_the_same_end(
    tmp_path, reference_state
):
    """Rank 0's manifest write of step TRAP fails (a directory stands where the manifest goes, placed while the run
    holds after its first commit, since a fresh start clears steps it does not know): every rank says the step was not
    committed, then that the next one was, and the run ends where an uninterrupted one does, bit for bit."""
    trap, hold = 4, Hold(tmp_path, 3)
    storage = tmp_path / "run"
    command = train_command(storage, "iterations=8", "checkpoint.keep_last=8", hold.override, ranks=2)
    env = child_env({ENV_DIR: str(tmp_path / "heartbeat"), "PYTHONPATH": str(TESTS)})
    proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    hold.held()
    wait_for(lambda: 2 in manifests(storage), "step 2 committed")
    blocker = storage / "checkpoints" / f"step-{trap:09d}" / "MANIFEST.json"
    blocker.mkdir(parents=True)
    hold.release()
    output, _ = proc.communicate(timeout=300)
    assert proc.returncode == 0, output[-3000:]
    assert blocker.is_dir() and not list(blocker.iterdir())
    blocker.rmdir()
    assert trap not in manifests(storage)
    for rank in (0, 1):
        assert re.search(rf"rank {rank}: checkpoint step {trap} not committed, earlier steps intact \(commit:", output)
    retried = {int(step) for step in re.findall(r"rank \d: checkpoint step (\d+) committed: saves work again", output)}
    assert len(retried) == 1 and output.count("saves work again") == 2, "both ranks name the same step"
    assert trap < retried.pop() in manifests(storage)
    assert final_manifest(storage)["state_sha256"] == reference_state(8)


@pytest.mark.waits
def test_a_commit_whose_answer_was_lost_counts_when_its_manifest_landed_and_is_never_deleted_unseen(s3_url):
    """The manifest's PUT is done by S3 but its answer never arrives (a reset connection, every try): a direct look
    finds the manifest, and the step is committed. When the storage stops answering right after that PUT, the look
    fails too: the step is left unsettled, and retention (keep_last=1) does not delete it at the next commit."""
    url, options = s3_url
    outage = threading.Event()

    def lose(method: str, path: str) -> bool:
        if outage.is_set():
            return True
        manifest = method == "PUT" and path.split("?")[0].endswith(f"/{step_dir(3)}/{MANIFEST}")
        if manifest:
            outage.set()  # this PUT is done; from now on no answer comes back
        return manifest or (method == "PUT" and path.split("?")[0].endswith(f"/{step_dir(2)}/{MANIFEST}"))

    proxy = StoreProxy(options["endpoint_url"], lose=lose)
    try:
        storage = Storage.open(url, {**options, "endpoint_url": proxy.endpoint_url}, retries=1)
        writer = StepWriter(storage, CheckpointConfig(keep_last=1), RankInfo(0, 1, 0), None, print)

        def save(step: int):
            state = {"common.pt": {"ftrain": {}, "actor_state_dict": {"weights": torch.full((4,), float(step))}}}
            return writer.save(step, state, {"iteration": step}, False)

        assert save(1).result is Result.COMMITTED
        assert save(2).result is Result.COMMITTED  # every answer to its manifest's PUT lost; the look finds it
        assert save(3).result is Result.FAILED and outage.is_set()
        outage.clear()
        assert save(4).result is Result.COMMITTED  # retention: keep the last one, delete 1 and 2, but not 3 unseen
    finally:
        proxy.close()
    direct = Storage.open(url, options)
    assert {info.step: info.status for info in scan(direct)} == {4: VERIFIED, 3: VERIFIED}


@pytest.mark.waits  # a throttled link: the run waits for it
def test_on_a_link_slower_than_training_every_pinned_step_and_milestone_is_saved_and_kept(tmp_path, s3_url) -> None:
    """Saves slower than iterations (a slow link) keep the writer busy with two in flight: a save due then was dropped,
    a pinned step's and a milestone's too, with no line, so that retention had nothing to keep. Now such a step waits
    for the oldest save, and a dropped save comes at the next free boundary. Random intervals, pins and milestones."""
    url, options = s3_url
    proxy = StoreProxy(options["endpoint_url"], rate=300_000)  # a save (~120 KB) takes ~0.4 s, an iteration ~0.02 s
    draw = random.Random()
    seed = draw.randrange(2**31)
    draw.seed(seed)
    cases = []
    try:
        for number in range(3):
            iterations, interval, keep_every = 24, draw.choice([2, 3]), draw.choice([5, 7, 9])
            pinned = sorted(draw.sample(range(1, iterations), 3))
            storage = f"{url}-{number}"
            overrides = [f"iterations={iterations}", f"checkpoint.interval={interval}", "checkpoint.spool=false"]
            overrides += [f"checkpoint.keep_every={keep_every}", f"checkpoint.pinned={pinned}"]
            overrides += ["checkpoint.keep_last=1", "checkpoint.keep_best=0", "log.console=false"]
            overrides += [f"storage.options.{key}={value}" for key, value in options.items() if key != "endpoint_url"]
            overrides += [f"storage.options.endpoint_url={proxy.endpoint_url}", f"log_dir={tmp_path / str(number)}"]
            train_here(load_config(SMOKE, overrides, storage=storage))
            kept = {info.step for info in scan(Storage.open(storage, options)) if info.status == VERIFIED}
            promised = {*pinned, *range(keep_every, iterations + 1, keep_every), iterations}
            assert kept == promised, f"seed {seed}: interval {interval}, keep_every {keep_every}, pinned {pinned}"
            cases.append(f"interval {interval}, keep_every {keep_every}, pinned {pinned}")
    finally:
        proxy.close()
    print(f"every promised step saved and kept in {len(cases)} runs (seed {seed}): {'; '.join(cases)}")


def test_the_closing_hint_names_storage_options_only_where_the_storage_takes_them(tmp_path, capsys) -> None:
    """A local path takes no storage options (``play --storage-option`` refuses them there): the closing line told the
    user to pass them to ``play`` and ``export`` where a run on a local path had ``storage.options`` in its config."""
    hint = "(with the storage options of this run: --storage-option KEY=VALUE)"
    for storage, shown in ((str(tmp_path / "local"), False), (f"memory://ftrain-test/{uuid.uuid4().hex}", True)):
        overrides = ["iterations=1", "storage.options.key=K", "log.console=false", f"log_dir={tmp_path / str(shown)}"]
        train_here(load_config(SMOKE, overrides, storage=storage))
        said = capsys.readouterr().out
        assert "[ftrain] play it: ftrain play " in said and (hint in said) == shown, said


def test_a_best_metric_the_run_does_not_record_is_said_once_at_its_first_commit(tmp_path, capsys) -> None:
    """Hooks add metrics of their own, so only a commit can tell: keep_best would keep no step by such a name."""
    said = {}
    for metric in ("mean_retrun", "eval_return", "mean_return"):  # a typo; a metric of evaluation, which is off
        overrides = ["iterations=6", "checkpoint.interval=2", f"checkpoint.best_metric={metric}", "log.console=false"]
        url = f"memory://ftrain-test/{uuid.uuid4().hex}"
        config = load_config(SMOKE, [*overrides, f"log_dir={tmp_path / metric}"], storage=url)
        train_here(config)
        said[metric] = [line for line in capsys.readouterr().out.splitlines() if "checkpoint.best_metric=" in line]
    for metric in ("mean_retrun", "eval_return"):
        assert len(said[metric]) == 1, said
        line = said[metric][0]
        assert f"checkpoint.best_metric={metric} is not a metric of this run" in line, line
        assert ", so keep_best keeps no step by it: use one of " in line and "mean_return" in line, line
    assert "this run (did you mean mean_return?), so" in said["mean_retrun"][0]
    assert said["mean_return"] == []


def test_a_step_retention_cannot_delete_is_said_once_and_again_when_it_goes(tmp_path) -> None:
    """A step that cannot be deleted (here: immutable, as a snapshot-protected or read-only directory is) is kept
    intact and tried again at every commit, in one line, not one per commit; a line says when it finally goes."""
    storage = Storage.open(str(tmp_path / "run"))
    lines: list[str] = []
    writer = StepWriter(storage, CheckpointConfig(keep_last=1), RankInfo(0, 1, 0), None, lines.append)

    def save(step: int):
        state = {"common.pt": {"ftrain": {}, "actor_state_dict": {"weights": torch.full((4,), float(step))}}}
        return writer.save(step, state, {"iteration": step}, False)

    assert save(1).result is Result.COMMITTED
    stuck = tmp_path / "run" / step_dir(1)
    if not shutil.which("chattr") or subprocess.run(["chattr", "+i", str(stuck)], capture_output=True).returncode:
        pytest.skip("chattr +i is not available here")
    try:
        for step in range(2, 7):
            assert save(step).result is Result.COMMITTED
    finally:
        subprocess.run(["chattr", "-i", str(stuck)])
    said = [line for line in lines if "could not be deleted" in line]
    assert len(said) == 1 and said[0].startswith("retention: checkpoint step 1 could not be deleted"), lines
    assert verify_step(storage, 1).ok and {info.step for info in scan(storage)} == {1, 6}
    assert save(7).result is Result.COMMITTED
    assert lines[-1] == "retention: checkpoint step 1 deleted now", lines
    assert {info.step for info in scan(storage)} == {7}
