"""Resuming at another world size: the learned state loads exactly, rank r keeps rank r's environments, new ranks
start fresh from (seed, rank, step), and the result depends on (checkpoint, new world size) only; with
``env.total_envs`` every environment goes on by its global index, and the training does not change."""

from __future__ import annotations

import csv
import random
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from ftrain.ckpt.resume import check_compatible
from ftrain.config import load_config
from ftrain.errors import UserError
from ftrain.supervise.options import SupervisorOptions, parse_nodes
from ftrain.supervise.supervisor import with_nproc

from helpers import REPO, SMOKE, child_env, final_manifest, free_port, manifests, run_train

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def two_rank_step(tmp_path_factory) -> str:
    """Step 4 of a 2-rank run, as a checkpoint URL."""
    storage = tmp_path_factory.mktemp("resize") / "run"
    run_train(storage, "iterations=4", ranks=2, supervised=True)
    return str(storage / "checkpoints" / "step-000000004")


@pytest.fixture(scope="module")
def resumed(tmp_path_factory, two_rank_step: str) -> Callable[..., tuple[Path, str]]:
    """``resumed(name, ranks, *overrides)``: the storage and output of a run to step 8 from ``two_rank_step`` at
    ``ranks``, run once per name in this module (the tests share the runs: each is a torchrun start of up to 3
    workers)."""
    runs: dict[str, tuple[Path, str]] = {}

    def run(name: str, ranks: int, *overrides: str) -> tuple[Path, str]:
        if name not in runs:
            storage = tmp_path_factory.mktemp(name) / "run"
            resume = f"resume={two_rank_step}"
            result = run_train(storage, "iterations=8", resume, *overrides, ranks=ranks, supervised=True)
            runs[name] = storage, result.stdout
        return runs[name]

    return run


@pytest.mark.parametrize("ranks", [1, 3])
def test_a_resize_is_a_function_of_checkpoint_and_world_size(resumed, two_rank_step: str, ranks: int) -> None:
    digests, logs = [], []
    for attempt in ("a", "b"):
        storage, output = resumed(f"{ranks}-ranks-{attempt}", ranks)
        logs.append(output)
        manifest = final_manifest(storage)
        assert (manifest["step"], manifest["world_size"]) == (8, ranks)
        assert manifest["world_sizes"] == [[0, 2], [4, ranks]]
        assert len(manifest["files"]) == ranks + 1
        digests.append(manifest["state_sha256"])
    assert digests[0] == digests[1], "two resumes of one step at one world size must train the same"
    assert f"resized from 2 to {ranks} ranks at step 4" in logs[0]
    now = "data-parallel (3 ranks: a split needs an even number)" if ranks == 3 else "on one rank"
    assert f"the update was split until step 4; from here on: {now}" in logs[0]
    before, after = (update_split(path / "metrics.csv") for path in (Path(two_rank_step).parents[1], storage))
    assert (set(before), set(after)) == ({1, 2, 3, 4}, {5, 6, 7, 8})  # the kind, iteration by iteration
    assert set(before.values()) == {1.0} and set(after.values()) == {0.0}
    if ranks == 3:
        assert "rank 2 starts with fresh ones" in logs[0] and "3 x 4 envs" in logs[0]
    else:
        assert "the shards of rank 1 are dropped" in logs[0]


def update_split(metrics: Path) -> dict[int, float]:
    with metrics.open() as file:
        return {int(row["iteration"]): float(row["update_split"]) for row in csv.DictReader(file)}


def test_growing_changes_training_and_the_same_size_continues_bit_for_bit(resumed, reference_state) -> None:
    same, output = resumed("2-ranks", 2)
    assert "resized" not in output
    assert final_manifest(same)["state_sha256"] == reference_state(8)  # as if never stopped at step 4
    grown, _ = resumed("3-ranks-a", 3)
    assert final_manifest(same)["world_sizes"] == [[0, 2]]
    assert final_manifest(same)["state_sha256"] != final_manifest(grown)["state_sha256"]
    assert sorted(manifests(grown)) == [6, 8]


def test_gloo_instead_of_shared_memory_trains_the_same_bits_at_two_ranks_and_other_last_bits_at_three(
    resumed, reference_state
) -> None:
    """``shared_memory_all_reduce=false`` sums the gradients with gloo: at two ranks the order of a sum of two cannot
    matter, so the run is the uninterrupted reference's bit for bit; at three gloo sums in another order than the
    shared memory's rank order, so the switch shows (and is why it is a config change at resume)."""
    gloo = "shared_memory_all_reduce=false"
    assert final_manifest(resumed("2-ranks-gloo", 2, gloo, "allow_config_change=true")[0])["state_sha256"] == (
        reference_state(8)
    )
    three = final_manifest(resumed("3-ranks-a", 3)[0])["state_sha256"]
    assert final_manifest(resumed("3-ranks-gloo", 3, gloo, "allow_config_change=true")[0])["state_sha256"] != three


EXACT = ["env.total_envs=8", "algorithm.schedule_iterations=8"]
"""A run whose ranks share 8 environments: at 1 and 2 ranks one rank's arithmetic (a split update of teams of one,
inferences whose rows do not depend on the batch's size), so resizes between them must not change a bit."""


def test_with_total_envs_any_resize_schedule_between_one_and_two_ranks_trains_bit_for_bit(tmp_path) -> None:
    """Random schedules of world sizes (1 or 2) and resize steps, ``env.total_envs`` fixed: every environment goes on
    by its global index, so each schedule ends with the state of the run that was never resized. The first leg may
    count the same environments per rank (``env.num_envs``, as the shipped configs did before they counted them in
    all): the next leg takes its step without ``allow_config_change``."""
    reference = tmp_path / "reference"
    run_train(reference, "iterations=8", *EXACT, ranks=1)
    expected = final_manifest(reference)["state_sha256"]
    seed = random.SystemRandom().randrange(2**31)  # a fresh draw each run: printed, to replay a failure
    draw = random.Random(seed)
    schedules = []
    for number in range(2):
        steps = sorted(draw.sample(range(1, 8), 2))
        first = draw.choice([1, 2])
        sizes = [first, 3 - first, draw.choice([1, 2])]  # at least one resize
        per_rank = number == 0  # one schedule of each counting, every run
        storage, outputs = tmp_path / f"schedule-{number}", []
        for leg, (size, step) in enumerate(zip(sizes, [*steps, 8], strict=True)):
            counted = [f"env.num_envs={8 // size}", *EXACT[1:]] if per_rank and leg == 0 else EXACT
            outputs.append(run_train(storage, f"iterations={step}", *counted, ranks=size).stdout)
        manifest = final_manifest(storage)
        schedules.append([*zip(sizes, [*steps, 8], strict=True), "per rank first" if per_rank else "in all"])
        assert manifest["state_sha256"] == expected, f"schedule {schedules[-1]} (seed {seed})"
        assert "every environment goes on" in outputs[1]
        assert ("the same environments, counted per rank or in all" in outputs[1]) == per_rank, outputs[1]
    print(f"{len(schedules)} resize schedules ((ranks, to step), counting), seed {seed}, all as one rank: {schedules}")


def test_a_run_counted_in_all_goes_on_counted_per_rank_only_with_the_same_environments(tmp_path) -> None:
    """The other way round: a step counted in all (``env.total_envs``) goes on under ``env.num_envs`` only at its
    world size with as many per rank (bit for bit); another total, or the same total at another world size (where only
    a count in all hands the environments on), is refused with the count to set."""
    storage, reference = tmp_path / "run", tmp_path / "reference"
    run_train(storage, "iterations=4", *EXACT, ranks=2, supervised=True)  # warm workers: cheaper
    manifest = final_manifest(storage)
    refusals = {
        1: "(2 ranks x 4), the config counts env.num_envs=8 per rank at 1 rank, and a resize hands them on",
        2: ("(2 ranks x 4), the config counts env.num_envs=8 per rank at 2 ranks: set env.total_envs=8 instead"),
    }
    for world, refusal in refusals.items():
        config = load_config(SMOKE, ["env.num_envs=8", EXACT[1]])
        with pytest.raises(UserError, match=re.escape(f"checkpoint step 4 has 8 environments in all {refusal}")):
            check_compatible(config, 4, manifest, world)
    went_on = run_train(storage, "iterations=8", "env.num_envs=4", EXACT[1], ranks=2, supervised=True)
    assert "the same environments, counted per rank or in all" in went_on.stdout, went_on.stdout
    run_train(reference, "iterations=8", *EXACT, ranks=1)
    assert final_manifest(storage)["state_sha256"] == final_manifest(reference)["state_sha256"]


def test_supervise_without_nproc_per_node_resumes_at_the_world_size_it_was_trained_at(tmp_path, reference_state):
    """The command that started a 2-rank run, less ``--nproc-per-node``, goes on at 2 ranks (bit for bit, as if never
    stopped), and says so; the flag given resizes as before. A fresh storage starts at 1 rank."""
    storage = tmp_path / "run"
    run_train(storage, "iterations=4", ranks=2, supervised=True)
    command = [sys.executable, "-m", "ftrain", "supervise", "configs/smoke.yaml", "--storage", str(storage)]
    again = subprocess.run([*command, "iterations=8"], cwd=REPO, env=child_env(), capture_output=True, text=True)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "2 workers, as step 4 was trained (--nproc-per-node N to resize)" in again.stderr, again.stderr
    assert "resized" not in again.stdout + again.stderr
    assert final_manifest(storage)["state_sha256"] == reference_state(8)
    resized = run_train(storage, "iterations=10", ranks=1, supervised=True)  # --nproc-per-node=1, given
    assert "resized from 2 to 1 ranks at step 8" in resized.stdout
    fresh = subprocess.run(
        [*command[:-1], str(tmp_path / "fresh"), "iterations=1"],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
    )
    assert fresh.returncode == 0 and "workers" not in fresh.stderr, fresh.stderr[-3000:]
    assert final_manifest(tmp_path / "fresh")["world_size"] == 1


def test_the_workers_a_supervisor_starts_without_nproc_per_node(tmp_path, two_rank_step, monkeypatch) -> None:
    """What ``with_nproc`` reads, from real storages: the storage's own newest step, else ``resume=``'s step; 1 on a
    fresh storage, on a storage that does not answer (and it says so), and for a step trained at more ranks than this
    node has CPUs (and it says so)."""

    def chosen(storage: str, *overrides: str, options: dict | None = None) -> tuple[int, str]:
        config = load_config(str(REPO / "configs/smoke.yaml"), list(overrides), storage)
        config.storage.options = options or {}
        unset = SupervisorOptions(nproc_per_node=None)
        resolved, said = with_nproc(unset, parse_nodes(unset), config)
        return resolved.nproc_per_node, said

    trained = str(Path(two_rank_step).parents[1])
    cases = {
        "a fresh storage": (chosen(str(tmp_path / "fresh")), (1, "")),
        "the run's own storage": (
            chosen(trained),
            (2, "2 workers, as step 4 was trained (--nproc-per-node N to resize)"),
        ),
        "resume= into a fresh one": (chosen(str(tmp_path / "new"), f"resume={two_rank_step}")[0], 2),
    }
    nobody = {"endpoint_url": f"http://127.0.0.1:{free_port()}", "key": "k", "secret": "s"}  # credentials: it is asked
    down = chosen("s3://bucket/run", options=nobody)
    cases["a storage that does not answer"] = (down[0], 1)
    assert "the storage did not say within 5 s how many ranks its run has: 1 worker" in down[1], down
    monkeypatch.setattr("os.cpu_count", lambda: 1)
    small = chosen(trained)
    cases["more ranks than CPUs"] = (
        small,
        (1, "step 4 was trained at 2 ranks, more than this node's 1 CPUs: 1 worker (--nproc-per-node N to choose)"),
    )
    for case, (got, expected) in cases.items():
        assert got == expected, f"{case}: {got}"
    print(f"{len(cases)} cases of the workers chosen without --nproc-per-node")
