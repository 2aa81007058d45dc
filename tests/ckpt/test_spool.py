"""The spool's rule for when a spooled step may stand in for the storage's newest (``ftrain/ckpt/spool.py``), on real
local storages: only when it continues the storage's history, and while the storage does not answer, only for the
holder of the storage's lease that wrote it (its run and generation)."""

from __future__ import annotations

import pytest

from ftrain.ckpt.format import commit, write_file
from ftrain.ckpt.spool import KEEP, Spool
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError
from ftrain.identity import GENERATION_ENV, RUN_ID_ENV

REMOTE = "s3://bucket/run"


def spool_with(tmp_path, monkeypatch, steps: dict[int, tuple[str, int | None]], generation: str = "3") -> Spool:
    """A spool holding ``steps`` (step: (state digest, base)), written for ``generation`` of run ``job``."""
    monkeypatch.setenv(RUN_ID_ENV, "job")
    monkeypatch.setenv(GENERATION_ENV, generation)
    spool = Spool(Storage.open(str(tmp_path / "spool")), REMOTE)
    for step, (digest, base) in steps.items():
        entry = spool.write(step, "common.pt", digest.encode())
        spool.commit(step, {"common.pt": entry}, {"state_sha256": digest}, base)
    return spool


def remote_step(tmp_path, step: int, digest: str) -> tuple[int, dict]:
    """``(step, manifest)`` of a step committed to a storage standing in for the remote one."""
    storage = Storage.open(str(tmp_path / "remote"))
    entry = write_file(storage, step, "common.pt", digest.encode())
    return step, commit(storage, step, {"common.pt": entry}, {"state_sha256": digest})


def test_a_newer_spooled_step_on_the_storages_newest_is_resumed_from(tmp_path, monkeypatch):
    spool = spool_with(tmp_path, monkeypatch, {30: ("c", 20)})
    assert spool.newest(remote_step(tmp_path, 20, "b"), True, print)[0] == 30


def test_the_storages_newest_step_in_the_spool_with_the_same_state_tells_the_history_too(tmp_path, monkeypatch):
    spool = spool_with(tmp_path, monkeypatch, {20: ("b", 10), 30: ("c", 10)})  # 20 committed, not yet heard of
    assert spool.newest(remote_step(tmp_path, 20, "b"), True, print)[0] == 30


def test_a_spooled_step_that_does_not_continue_the_storage_is_not_resumed_from(tmp_path, monkeypatch):
    lines = []
    spool = spool_with(tmp_path, monkeypatch, {20: ("x", 10), 30: ("c", 10)})
    assert spool.newest(remote_step(tmp_path, 20, "b"), True, lines.append) is None  # another history's step 20
    assert lines == [
        f"not resuming from spooled step 30 ({spool.storage.url}): the storage's newest step 20 is not in its history"
    ]


def test_a_storage_emptied_since_goes_on_from_this_runs_spool_and_refuses_another_runs(tmp_path, monkeypatch):
    """Emptied since the spool's steps were written on its step 20: they are the only copy of what was trained. The
    run that spooled them goes on from them; another run (the same command again, the storage emptied to start over,
    or another server with the same bucket) is refused, and the spool kept, with both ways on."""
    lines = []
    spool = spool_with(tmp_path, monkeypatch, {20: ("b", 10), 30: ("c", 20)})
    assert spool.newest(None, True, lines.append)[0] == 30 and lines == []
    monkeypatch.setenv(RUN_ID_ENV, "another")
    said = r"s3://bucket/run holds no step, but the spool holds step 30 of its history, spooled on its step 20 by an"
    with pytest.raises(
        UserError, match=said + r" earlier run \(.*\): to go on from it, copy that directory to .*resume=never"
    ):
        Spool(spool.storage, REMOTE).newest(None, True, lines.append)
    assert [info.step for info in scan(spool.storage)] == [30, 20] and lines == []


def test_the_storage_newer_than_the_spool_wins(tmp_path, monkeypatch):
    spool = spool_with(tmp_path, monkeypatch, {30: ("c", 20)})
    assert spool.newest(remote_step(tmp_path, 30, "c"), True, print) is None


def test_a_fresh_run_whose_storage_never_committed_resumes_from_its_spool(tmp_path, monkeypatch):
    assert spool_with(tmp_path, monkeypatch, {5: ("a", None)}).newest(None, True, print)[0] == 5


def test_while_the_storage_is_down_only_the_holder_that_spooled_may_resume(tmp_path, monkeypatch):
    spool = spool_with(tmp_path, monkeypatch, {30: ("c", 20)}, generation="3")
    assert spool.newest(None, False, print)[0] == 30
    monkeypatch.setenv(GENERATION_ENV, "4")  # the same command again: a new holder of the storage
    lines = []
    assert Spool(spool.storage, REMOTE).newest(None, False, lines.append) is None
    assert "another holder of the storage" in lines[0]
    monkeypatch.delenv(GENERATION_ENV)  # no lease held for this process
    assert Spool(spool.storage, REMOTE).newest(None, False, print) is None


def test_another_storages_steps_are_ignored_and_only_the_newest_steps_are_kept(tmp_path, monkeypatch):
    spool = spool_with(tmp_path, monkeypatch, {step: (str(step), None) for step in range(1, KEEP + 3)})
    assert sorted(int(name[5:]) for name in spool.storage.list_dirs("checkpoints")) == list(range(3, KEEP + 3))
    assert Spool(spool.storage, "s3://bucket/other").newest(None, True, print) is None


def test_a_corrupt_spooled_step_newer_than_the_storages_is_told_not_skipped_in_silence(tmp_path, monkeypatch):
    """The step before it (verified) is resumed from, and one line says why the newer one is not."""
    spool = spool_with(tmp_path, monkeypatch, {30: ("c", 20), 40: ("d", 20)})
    shard = tmp_path / "spool" / "checkpoints" / "step-000000040" / "common.pt"
    shard.write_bytes(shard.read_bytes()[:-1])  # cut short
    lines = []
    assert spool.newest(remote_step(tmp_path, 20, "b"), True, lines.append)[0] == 30
    assert lines == [
        f"not resuming from spooled step 40 ({spool.storage.url}): it is corrupt (common.pt: size mismatch: "
        "0 bytes, manifest says 1)"
    ]
    lines.clear()
    assert spool.newest(remote_step(tmp_path, 50, "e"), True, lines.append) is None  # the storage has newer: no word
    assert lines == []


def test_resume_into_the_spool_is_refused_by_any_name_before_the_start(tmp_path, monkeypatch):
    """A start that does not resume from the spool empties it (on several nodes, before anything): ``resume=`` a step
    there is refused, however it is spelt, before the run starts; a path beside it, or a spool switched off, is
    taken."""
    from ftrain.ckpt.spool import check_place
    from ftrain.config import load_config

    monkeypatch.chdir(tmp_path)
    (tmp_path / "logs" / "spool" / "checkpoints").mkdir(parents=True)
    (tmp_path / "link").symlink_to(tmp_path / "logs")
    run = ["storage.url=s3://bucket/run", f"log_dir={tmp_path / 'logs'}"]
    inside = [
        "logs/spool/checkpoints/step-000000005",
        str(tmp_path / "link" / "spool" / "checkpoints"),
        "other/../logs/spool",
        f"file://{tmp_path}/logs/spool/checkpoints/step-000000005",
    ]
    for resume in inside:
        with pytest.raises(UserError, match=r"is in this run's spool, which a start that does not resume from it"):
            check_place(load_config(None, [*run, f"resume={resume}"]))
    for resume in ["logs/spool2/checkpoints/step-000000005", "s3://bucket/run/checkpoints/step-000000005"]:
        check_place(load_config(None, [*run, f"resume={resume}"]))
    check_place(load_config(None, [*run, f"resume={inside[0]}", "checkpoint.spool=false"]))
    print(f"{len(inside)} spellings refused, 3 taken")
