"""Fencing (``ftrain/ckpt/fence.py``) on a local storage and on S3 (moto): a commit below the lease's generation, or
below the newest (generation, attempt) that committed, is refused and says so; each manifest names who committed."""

from __future__ import annotations

import json

import pytest
import torch

from ftrain.ckpt.fence import FENCE, Fence, Fenced
from ftrain.ckpt.lease import LEASE, Lease, Record
from ftrain.ckpt.save import Result, StepWriter
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.comm.group import RankInfo
from ftrain.config import CheckpointConfig
from ftrain.identity import ATTEMPT_ENV, GENERATION_ENV, RUN_ID_ENV, Identity


@pytest.fixture(params=["local", "s3"])
def storage(request, tmp_path) -> Storage:
    if request.param == "local":
        return Storage.open(str(tmp_path / "run"))
    return Storage.open(*request.getfixturevalue("s3_url"))


def save(storage: Storage, step: int, monkeypatch, identity: Identity | None, lines: list[str]):
    """One save of a one-rank world of ``identity`` through the real writer: its outcome."""
    for name in (RUN_ID_ENV, GENERATION_ENV, ATTEMPT_ENV):
        monkeypatch.delenv(name, raising=False)
    for name, value in (identity.env() if identity is not None else {}).items():
        monkeypatch.setenv(name, value)
    writer = StepWriter(storage, CheckpointConfig(), RankInfo(0, 1, 0), None, lines.append)
    state = {"weights": torch.full((4,), float(step))}
    return writer.save(step, {"common.pt": {"ftrain": {}, "actor_state_dict": state}}, {"iteration": step}, False)


def committed(storage: Storage) -> list[tuple]:
    manifests = [info.manifest for info in scan(storage) if info.manifest]
    return [(m["step"], m["run_id"], m["generation"], m.get("attempt")) for m in manifests]


def test_an_older_attempt_commits_nothing_once_a_newer_one_has(storage, monkeypatch):
    lines: list[str] = []
    Lease(storage, "run-a", print).acquire()
    generation = 1
    assert save(storage, 10, monkeypatch, Identity("run-a", generation, 1), lines).result is Result.COMMITTED
    assert save(storage, 20, monkeypatch, Identity("run-a", generation, 2), lines).result is Result.COMMITTED
    late = save(storage, 15, monkeypatch, Identity("run-a", generation, 1), lines)  # the node that was cut off
    assert late.result is Result.FENCED and "attempt 2 of generation 1 has committed" in late.detail
    assert any(line.startswith("checkpoint step 15 refused") for line in lines)
    assert committed(storage) == [(20, "run-a", 1, 2), (10, "run-a", 1, 1)]
    assert save(storage, 30, monkeypatch, Identity("run-a", generation, 2), lines).result is Result.COMMITTED


def test_a_newer_plan_fences_off_every_attempt_of_an_older_one_as_soon_as_it_takes_its_generation(storage, monkeypatch):
    """Node 0's supervisor started again makes a new plan at the next generation, whose first attempt is 0: the nodes
    still running the old plan's attempt 7 commit nothing more once the lease has the new generation, even before
    the new plan commits."""
    first = Lease(storage, "run-a", print)
    first.acquire()
    assert save(storage, 10, monkeypatch, Identity("run-a", 1, 7), []).result is Result.COMMITTED
    again = Lease(storage, "run-a", print)
    assert again.hold(advance=True) is None  # node 0 again: generation 2
    late = save(storage, 20, monkeypatch, Identity("run-a", 1, 8), [])
    assert late.result is Result.FENCED and "newer start of run run-a (generation 2; this one's is 1)" in late.detail
    assert save(storage, 20, monkeypatch, Identity("run-a", 2, 0), []).result is Result.COMMITTED
    with pytest.raises(Fenced):
        Fence(storage, Identity("run-a", 1, 9)).check()
    assert json.loads(storage.read(FENCE)) == {"run_id": "run-a", "generation": 2, "attempt": 0}
    assert committed(storage) == [(20, "run-a", 2, 0), (10, "run-a", 1, 7)]
    again.release()


def test_one_node_alone_is_checked_against_the_lease_only(storage, monkeypatch):
    """Without an attempt (one node: its supervisor runs one attempt at a time) nothing is written but the manifest,
    and a newer holder of the lease ends the run's commits as lost (exit 8), not fenced."""
    Lease(storage, "run-a", print).acquire()
    assert save(storage, 10, monkeypatch, Identity("run-a", 1), []).result is Result.COMMITTED
    assert not storage.exists(FENCE) and committed(storage) == [(10, "run-a", 1, None)]
    storage.write_replace(LEASE, Record("run-b", 2, 60.0, ()).encode())  # another run took it (run-a was paused)
    lost = save(storage, 20, monkeypatch, Identity("run-a", 1), [])
    assert lost.result is Result.LEASE_LOST and "taken by run run-b (generation 2; this run's is 1)" in lost.detail


def test_a_lease_record_deleted_by_hand_starts_again_after_the_newest_generation_that_committed(storage, monkeypatch):
    """``LEASE.json`` is the one file a user is told to delete (when it cannot be read): the next holder's generation
    then comes after the newest that committed (``FENCE.json``), so its commits are not fenced off; and a commit of
    a run whose id is not the lease's is refused whatever its generation (another run holds the storage)."""
    assert save(storage, 10, monkeypatch, Identity("run-a", 7, 2), []).result is Result.COMMITTED
    lease = Lease(storage, "run-a", print)
    lease.acquire()
    assert lease.generation == 8
    assert save(storage, 20, monkeypatch, Identity("run-a", 8, 0), []).result is Result.COMMITTED
    stranger = save(storage, 30, monkeypatch, Identity("run-b", 9, 0), [])
    assert stranger.result is Result.LEASE_LOST and "taken by run run-a" in stranger.detail


def test_an_unreadable_fence_record_counts_as_none_and_is_written_over(storage):
    storage.write_replace(FENCE, b"{not json")
    assert Fence(storage, Identity("run-a", 1, 3)).check() == {"run_id": "run-a", "generation": 1, "attempt": 3}
    assert json.loads(storage.read(FENCE)) == {"run_id": "run-a", "generation": 1, "attempt": 3}


def test_without_an_identity_nothing_is_fenced_or_written(tmp_path, monkeypatch):
    storage = Storage.open(str(tmp_path / "run"))
    assert save(storage, 10, monkeypatch, None, []).result is Result.COMMITTED
    assert Fence.from_env(storage) is None
    assert not storage.exists(FENCE) and "generation" not in scan(storage)[0].manifest
