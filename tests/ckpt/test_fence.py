"""Fencing (``ftrain/ckpt/fence.py``) on a local storage and on S3 (moto): a save of an older generation of a run
is refused once a newer one has committed, and says so; another run's record does not fence a new run."""

from __future__ import annotations

import json

import pytest
import torch

from ftrain.ckpt.fence import FENCE, GENERATION_ENV, Fence, Fenced
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
    assert save(storage, 10, monkeypatch, "run-a:1", lines).result is Result.COMMITTED
    assert save(storage, 20, monkeypatch, "run-a:2", lines).result is Result.COMMITTED  # the others went on
    late = save(storage, 15, monkeypatch, "run-a:1", lines)  # the node that was cut off
    assert late.result is Result.FENCED and "fenced off: generation 2 has committed" in late.detail  # the rank stops
    assert any(line.startswith("checkpoint step 15 refused") for line in lines)
    assert [(info.step, info.manifest["generation"]) for info in scan(storage) if info.manifest] == [
        (20, ["run-a", 2]),
        (10, ["run-a", 1]),
    ]
    assert save(storage, 30, monkeypatch, "run-a:2", lines).result is Result.COMMITTED  # the same generation goes on


def test_a_new_run_is_not_fenced_by_the_record_of_an_earlier_one(storage, monkeypatch):
    assert save(storage, 10, monkeypatch, "run-a:7", []).result is Result.COMMITTED
    assert save(storage, 20, monkeypatch, "run-b:0", []).result is Result.COMMITTED  # generation 0 < 7, another run
    Fence(storage, "run-b", 1).check()
    with pytest.raises(Fenced, match="generation 1 has committed"):
        Fence(storage, "run-b", 0).check()


def test_an_unreadable_fence_record_counts_as_none_and_is_written_over(storage):
    storage.write_replace(FENCE, b"{not json")
    Fence(storage, "run-a", 3).check()
    assert json.loads(storage.read(FENCE)) == {"run": "run-a", "generation": 3}


def test_without_a_generation_nothing_is_fenced_or_written(tmp_path, monkeypatch):
    monkeypatch.delenv(GENERATION_ENV, raising=False)
    storage = Storage.open(str(tmp_path / "run"))
    assert Fence.from_env(storage) is None
    assert save(storage, 10, monkeypatch, "", []).result is Result.COMMITTED
    assert not storage.exists(FENCE) and "generation" not in scan(storage)[0].manifest
