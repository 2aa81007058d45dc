"""Fencing (``ftrain/ckpt/fence.py``) on a local storage and on S3 (moto): a save of an older generation of a run
is refused once a newer one has committed, and says so; another run's record does not fence a new run."""

from __future__ import annotations

import json

import pytest
import torch

from ftrain.ckpt.fence import FENCE, GENERATION_ENV, Fence, Fenced, epoch_of
from ftrain.ckpt.save import Result, StepWriter
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.config import CheckpointConfig
from ftrain.dist.group import RankInfo


@pytest.fixture(params=["local", "s3"])
def storage(request, tmp_path) -> Storage:
    if request.param == "local":
        return Storage.open(str(tmp_path / "run"))
    return Storage.open(*request.getfixturevalue("s3_url"))


def save(storage: Storage, step: int, monkeypatch, generation: str, lines: list[str]):
    """One save of a one-rank world of ``generation`` through the real writer: its outcome."""
    monkeypatch.setenv(GENERATION_ENV, generation)
    writer = StepWriter(storage, CheckpointConfig(), RankInfo(0, 1, 0), None, lines.append)
    state = {"weights": torch.full((4,), float(step))}
    return writer.save(step, {"common.pt": {"ftrain": {}, "actor_state_dict": state}}, {"iteration": step}, False)


def test_an_older_generation_commits_nothing_once_a_newer_one_has(storage, monkeypatch):
    lines: list[str] = []
    epoch = epoch_of(storage, "run-a")
    assert save(storage, 10, monkeypatch, f"run-a:{epoch}:1", lines).result is Result.COMMITTED
    assert save(storage, 20, monkeypatch, f"run-a:{epoch}:2", lines).result is Result.COMMITTED  # the others went on
    late = save(storage, 15, monkeypatch, f"run-a:{epoch}:1", lines)  # the node that was cut off
    assert late.result is Result.FENCED and "fenced off: generation 2 of epoch 1 is newer" in late.detail
    assert any(line.startswith("checkpoint step 15 refused") for line in lines)
    manifests = [info.manifest for info in scan(storage) if info.manifest]
    committed = [(manifest["step"], manifest["generation"], manifest["epoch"]) for manifest in manifests]
    assert committed == [(20, ["run-a", 2], 1), (10, ["run-a", 1], 1)]
    assert save(storage, 30, monkeypatch, f"run-a:{epoch}:2", lines).result is Result.COMMITTED  # it goes on


def test_a_newer_token_fences_off_every_attempt_of_an_older_one_as_soon_as_it_has_its_epoch(storage, monkeypatch):
    """Node 0's supervisor started again mints a new token, whose first attempt is 0: the nodes still running the
    old token's attempt 7 commit nothing more once the new token has taken its epoch, even before it commits."""
    old = epoch_of(storage, "token-1")
    assert save(storage, 10, monkeypatch, f"token-1:{old}:7", []).result is Result.COMMITTED
    new = epoch_of(storage, "token-2")
    assert (old, new) == (1, 2) and epoch_of(storage, "token-1") == 1  # an epoch is the token's for good
    late = save(storage, 20, monkeypatch, f"token-1:{old}:8", [])
    assert late.result is Result.FENCED and "generation -1 of epoch 2 is newer" in late.detail
    assert save(storage, 20, monkeypatch, f"token-2:{new}:0", []).result is Result.COMMITTED
    with pytest.raises(Fenced, match="generation 0 of epoch 2 is newer"):
        Fence(storage, "token-1", old, 9).check()
    record = json.loads(storage.read(FENCE))
    assert (record["run"], record["epoch"], record["generation"], record["epochs"]) == (
        "token-2",
        2,
        0,
        {"token-1": 1, "token-2": 2},
    )


def test_every_node_of_a_token_gets_the_same_epoch_from_the_storage_and_only_its_maker_numbers_it(storage):
    """On c10d only node 0's supervisor, which made the token, numbers it: a node still holding a token from before
    node 0 started again must not take an epoch above the newer token's. It waits, then takes 0: fenced off."""
    assert epoch_of(storage, "token-a") == 1
    assert epoch_of(storage, "token-a", allocate=False) == 1 and epoch_of(storage, "token-b") == 2
    assert epoch_of(storage, "token-stale", allocate=False, wait=0.2) == 0
    with pytest.raises(Fenced):
        Fence(storage, "token-stale", 0, 5).check()
    assert "token-stale" not in json.loads(storage.read(FENCE))["epochs"]


def test_an_unreadable_fence_record_counts_as_none_and_is_written_over(storage):
    storage.write_replace(FENCE, b"{not json")
    Fence(storage, "run-a", 1, 3).check()
    assert json.loads(storage.read(FENCE)) == {"run": "run-a", "epoch": 1, "generation": 3}


def test_without_a_generation_nothing_is_fenced_or_written(tmp_path, monkeypatch):
    monkeypatch.delenv(GENERATION_ENV, raising=False)
    storage = Storage.open(str(tmp_path / "run"))
    assert Fence.from_env(storage) is None
    assert save(storage, 10, monkeypatch, "", []).result is Result.COMMITTED
    assert not storage.exists(FENCE) and "generation" not in scan(storage)[0].manifest
