"""Resuming at another world size: the learned state loads exactly, rank r keeps rank r's environments, new ranks
start fresh from (seed, rank, step), and the result depends on (checkpoint, new world size) only."""

from __future__ import annotations

import pytest

from helpers import final_manifest, manifests, run_train

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def two_rank_step(tmp_path_factory) -> str:
    """Step 4 of a 2-rank run, as a checkpoint URL."""
    storage = tmp_path_factory.mktemp("resize") / "run"
    run_train(storage, "iterations=4", ranks=2)
    return str(storage / "checkpoints" / "step-000000004")


@pytest.mark.parametrize("ranks", [1, 3])
def test_a_resize_is_a_function_of_checkpoint_and_world_size(tmp_path, two_rank_step: str, ranks: int) -> None:
    digests, logs = [], []
    for attempt in ("a", "b"):
        storage = tmp_path / attempt
        result = run_train(storage, "iterations=8", f"resume={two_rank_step}", ranks=ranks)
        logs.append(result.stdout)
        manifest = final_manifest(storage)
        assert (manifest["step"], manifest["world_size"]) == (8, ranks)
        assert manifest["world_sizes"] == [[0, 2], [4, ranks]]
        assert len(manifest["files"]) == ranks + 1
        digests.append(manifest["state_sha256"])
    assert digests[0] == digests[1], "two resumes of one step at one world size must train the same"
    assert f"resized from 2 to {ranks} ranks at step 4" in logs[0]
    if ranks == 3:
        assert "rank 2 start with fresh ones" in logs[0] and "3 x 4 envs" in logs[0]
    else:
        assert "the shards of rank 1 are dropped" in logs[0]


def test_growing_changes_training_and_the_same_size_continues_bit_for_bit(tmp_path, two_rank_step: str) -> None:
    same = run_train(tmp_path / "same", "iterations=8", f"resume={two_rank_step}", ranks=2)
    assert "resized" not in same.stdout
    grown = tmp_path / "grown"
    run_train(grown, "iterations=8", f"resume={two_rank_step}", ranks=3)
    assert final_manifest(tmp_path / "same")["world_sizes"] == [[0, 2]]
    assert final_manifest(tmp_path / "same")["state_sha256"] != final_manifest(grown)["state_sha256"]
    assert sorted(manifests(grown)) == [6, 8]
