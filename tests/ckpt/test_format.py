import json
import os
import pathlib
import time

import pytest
import torch

from ftrain.ckpt.format import (
    CHECKPOINTS,
    CORRUPT,
    DIGEST,
    FORMAT_VERSION,
    INCOMPLETE,
    MANIFEST,
    QUARANTINE,
    QUARANTINED,
    VERIFIED,
    CorruptCheckpoint,
    FileEntry,
    StepInfo,
    commit,
    decode,
    encode,
    parse_checkpoint_url,
    read_manifest,
    read_verified,
    recorded_metrics,
    step_dir,
    verify_step,
    write_file,
)
from ftrain.ckpt.retention import delete_step, retention_plan
from ftrain.ckpt.steps import (
    ABANDONED_AFTER,
    ASIDE,
    clear_newer,
    quarantine,
    resolve_checkpoint_url,
    scan,
    select_resume,
    set_aside_steps,
    unquarantine,
)
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError

from failing_mount import failing_mount
from helpers import flip_shard_byte, make_step, step_path, truncate_shard


@pytest.fixture
def storage(tmp_path) -> Storage:
    return Storage.open(str(tmp_path / "run"))


def test_write_commit_verify_read_round_trip(storage_url):
    storage = Storage.open(*storage_url)
    manifest = make_step(storage, 120)
    assert manifest["format_version"] == FORMAT_VERSION and manifest["step"] == 120
    assert manifest["world_size"] == 2 and manifest["metrics"] == {"mean_return": 120.0}
    assert set(manifest["files"]) == {"common.pt", "rank-00000.pt", "rank-00001.pt"}

    raw = storage.read(step_path(120, MANIFEST)).decode()
    assert json.loads(raw) == manifest
    assert '\n  "step": 120,' in raw  # indented: readable by a human

    result = verify_step(storage, 120)
    assert result.ok and result.manifest == manifest
    common = read_verified(storage, 120, "common.pt", manifest)
    assert torch.equal(common["policy"]["weight"], torch.full((2, 3), 120.0))
    assert read_verified(storage, 120, "rank-00001.pt", manifest)["rank"] == 1
    [info] = scan(storage)
    assert (info.step, info.status, info.metrics) == (120, VERIFIED, {"mean_return": 120.0})
    assert info.size == sum(storage.list_files(step_dir(120)).values())


def test_a_committed_step_cannot_be_written_again(storage_url):
    storage = Storage.open(*storage_url)
    manifest = make_step(storage, 10)
    with pytest.raises(FileExistsError):
        write_file(storage, 10, "rank-00000.pt", encode({"other": 1}))
    entries = {name: FileEntry(**entry) for name, entry in manifest["files"].items()}
    with pytest.raises(FileExistsError):
        commit(storage, 10, entries, {"metrics": {"mean_return": -1.0}})
    assert read_manifest(storage, 10) == manifest


def test_commit_refuses_a_file_that_is_not_there(storage):
    entry = write_file(storage, 5, "common.pt", b"data")
    with pytest.raises(CorruptCheckpoint, match=r"rank-00000.pt is missing"):
        commit(storage, 5, {"common.pt": entry, "rank-00000.pt": entry}, {})
    with pytest.raises(ValueError, match="step"):
        commit(storage, 5, {"common.pt": entry}, {"step": 6})
    assert not storage.exists(step_path(5, MANIFEST))


def edit_manifest(storage: Storage, step: int, edit, older: bool = False) -> None:
    """Change a manifest as a hand or a bug would; ``older``: as an ftrain before manifests had their own digest."""
    manifest = json.loads(storage.read(step_path(step, MANIFEST)))
    edit(manifest)
    if older:
        del manifest[DIGEST]
    storage.write_replace(step_path(step, MANIFEST), json.dumps(manifest).encode())


EDITED = "MANIFEST.json: unusable: its content does not match its own digest"
CORRUPTIONS = {
    "flipped byte": (flip_shard_byte, "rank-00001.pt: sha256 mismatch"),
    "truncated shard": (truncate_shard, "rank-00001.pt: size mismatch"),
    "missing shard": (lambda s, step: s.delete(step_path(step, "rank-00001.pt")), "rank-00001.pt: missing"),
    "missing manifest": (lambda s, step: s.delete(step_path(step, MANIFEST)), "MANIFEST.json: missing"),
    "garbage manifest": (
        lambda s, step: s.write_replace(step_path(step, MANIFEST), b"\x00{garbage"),
        "MANIFEST.json: unusable: not valid JSON",
    ),
    "manifest nested too deep": (  # parsing it was a RecursionError: a traceback in every reader
        lambda s, step: s.write_replace(step_path(step, MANIFEST), b"[" * 5000 + b"]" * 5000),
        "MANIFEST.json: unusable: not valid JSON (nested too deep)",
    ),
    "manifest size disagrees": (
        lambda s, step: edit_manifest(s, step, lambda m: m["files"]["rank-00001.pt"].update(size=1)),
        EDITED,
    ),
    "manifest of another step": (lambda s, step: edit_manifest(s, step, lambda m: m.update(step=step + 1)), EDITED),
    "manifest counters changed": (lambda s, step: edit_manifest(s, step, lambda m: m.update(world_size=3)), EDITED),
    "older manifest size disagrees": (
        lambda s, step: edit_manifest(s, step, lambda m: m["files"]["rank-00001.pt"].update(size=1), older=True),
        "rank-00001.pt: size mismatch",
    ),
    "older manifest of another step": (
        lambda s, step: edit_manifest(s, step, lambda m: m.update(step=step + 1), older=True),
        "MANIFEST.json: unusable: wrong step",
    ),
}


def test_a_manifest_damaged_anywhere_never_verifies_with_other_content(storage):
    """Generated cases: one byte of a real manifest changed at 600 random places (a seeded draw), each on a fresh copy.
    None verifies with content other than what was committed, whether the damage leaves JSON (a key, a number, a
    digit of a digest) or not; the one that verifies is damage to the digest's own key, which leaves a manifest as an
    ftrain before the digest wrote it, its content intact."""
    import random

    make_step(storage, 30)
    original = storage.read(step_path(30, MANIFEST))
    committed = read_manifest(storage, 30)
    draw, still_json, intact = random.Random(30), 0, 0
    for _ in range(600):
        at = draw.randrange(len(original))
        damaged = bytearray(original)
        damaged[at] = draw.choice([b for b in b"0123456789abcdefXYZ_ .,:" if b != original[at]])
        storage.write_replace(step_path(30, MANIFEST), bytes(damaged))
        result = verify_step(storage, 30, full=False)
        if result.ok:
            near = {key for key in result.manifest if len(key) == len(DIGEST) and sum(map(str.__ne__, key, DIGEST)) < 2}
            read = {key: value for key, value in result.manifest.items() if key not in near}  # the key damaged
            assert read == {key: value for key, value in committed.items() if key != DIGEST}, damaged[at - 20 : at]
            intact += 1
        still_json += not result.ok and "not valid JSON" not in str(result.problems[0])
    print(
        f"600 damaged manifests: {600 - intact} refused ({still_json} of them still JSON), {intact} damaged in the "
        "digest's key only and read with the content committed"
    )
    assert still_json > 300 and intact < 60  # the key is 17 bytes of about 580
    storage.write_replace(step_path(30, MANIFEST), original)
    edit_manifest(storage, 30, lambda m: None, older=True)
    assert verify_step(storage, 30).ok


def test_an_older_manifest_with_a_field_of_another_type_is_corrupt_and_resume_goes_on_from_the_step_before(tmp_path):
    """Generated cases: a manifest without its digest (an ftrain's before it, or the digest's key itself damaged) with
    one field a reader uses given a value of another type or range: resume quarantines it and goes on from the step
    before, and ls, verify and the history read it without a traceback."""
    from ftrain.ckpt import commands as ckpt_commands
    from ftrain.ckpt.lineage import history

    fields = {
        "iteration": 30, "world_size": 2, "envs_per_rank": 4, "state_format": 4, "generation": 1, "attempt": 0,
        "parent": {"step": 20, "state_sha256": "a" * 64}, "world_sizes": [[0, 2]], "state_sha256": "b" * 64,
        "run_id": "r", "config_hash": "c", "config": {}, "metrics": {"mean_return": 1.0}, "robot": {}, "arithmetic": {},
    }  # fmt: skip
    number, string, mapping = ["x", -1, 1.5, True, None], [5, None, []], ["x", [], 5, None]
    wrong = {
        **dict.fromkeys(["iteration", "state_format", "generation"], number),
        **{key: [0, "2", 2.0, None] for key in ["world_size", "envs_per_rank"]},
        "attempt": ["0", -1, 1.5],
        "parent": ["x", [], {"step": "20"}, {"state_sha256": "a" * 64}],
        "world_sizes": ["x", [[0, "2"]], [0, 2], {}],
        **dict.fromkeys(["state_sha256", "run_id", "config_hash"], string),
        **dict.fromkeys(["config", "metrics", "robot", "arithmetic"], mapping),
    }
    assert wrong.keys() == fields.keys()
    checked = 0
    for key, values in wrong.items():
        for value in values:
            storage = Storage.open(str(tmp_path / f"run-{checked}"))
            make_step(storage, 20)
            manifest = make_step(storage, 30)
            older = {**{k: v for k, v in manifest.items() if k != DIGEST}, **fields, key: value}
            storage.write_replace(step_path(30, MANIFEST), json.dumps(older).encode())
            assert [info.status for info in scan(storage)] == [CORRUPT, VERIFIED], (key, value)
            history(scan(storage))
            assert ckpt_commands.ls(storage.url) == 0 and ckpt_commands.verify(storage.url) == 1
            assert select_resume(storage, log=lambda line: None)[0] == 20, (key, value)
            assert storage.exists(step_path(30, QUARANTINED))
            checked += 1
    print(f"{checked} older manifests with a field damaged: corrupt, quarantined, resumed from the step before")
    assert checked > 50


@pytest.mark.parametrize("case", CORRUPTIONS)
def test_damage_is_never_verified_and_the_reason_is_named(storage_url, case):
    storage = Storage.open(*storage_url)
    manifest = make_step(storage, 30)
    damage, reason = CORRUPTIONS[case]
    damage(storage, 30)
    result = verify_step(storage, 30)
    assert not result.ok
    assert any(str(problem).startswith(reason) for problem in result.problems), result.problems
    [info] = scan(storage, full=True)
    assert info.status == (INCOMPLETE if case == "missing manifest" else CORRUPT)
    if case in ("flipped byte", "truncated shard", "missing shard"):
        with pytest.raises(CorruptCheckpoint, match=r"rank-00001.pt"):
            read_verified(storage, 30, "rank-00001.pt", manifest)


@pytest.mark.parametrize("name", [MANIFEST, "rank-00001.pt"])
def test_a_directory_where_a_file_of_a_step_belongs_is_damage_and_resume_goes_on_from_the_step_before(tmp_path, name):
    """A local step with a directory in the place of its manifest or of a shard (a hand, a sync tool, a restore) is
    corrupt, named, and skipped: reading the manifest was "IsADirectoryError" in every command, and the supervisor
    crash-looped with "no step committed yet" beside two verified steps."""
    storage = Storage.open(str(tmp_path / "run"))
    make_step(storage, 10)
    make_step(storage, 20)
    place = tmp_path / "run" / step_path(20, name)
    place.unlink()
    place.mkdir()
    reason = f"{name}: unusable: a directory, not a file" if name == MANIFEST else f"{name}: missing"
    assert [str(problem) for problem in verify_step(storage, 20).problems] == [reason]
    assert [(info.step, info.status) for info in scan(storage, full=True)] == [(20, CORRUPT), (10, VERIFIED)]
    assert select_resume(storage, log=lambda line: None)[0] == 10


def test_the_cheap_scan_checks_sizes_the_full_one_digests(storage):
    make_step(storage, 10)
    make_step(storage, 20)
    flip_shard_byte(storage, 10)
    truncate_shard(storage, 20)
    assert [(i.step, i.status) for i in scan(storage)] == [(20, CORRUPT), (10, VERIFIED)]
    assert [(i.step, i.status) for i in scan(storage, full=True)] == [(20, CORRUPT), (10, CORRUPT)]


def test_a_step_copied_under_another_spelling_of_its_number_is_no_step(storage):
    """A copy of step 10 as ``step-0000000010`` was read as a second step 10 (two histories of one generation, and a
    ``prune --keep-line`` whose advice refused itself). Only the name ``step_dir`` gives a step is one: nine digits,
    or more without a leading zero."""
    for step in (8, 10, 1_000_000_000):
        make_step(storage, step)
    for name in storage.list_files(step_dir(10)):
        storage.write_replace(f"checkpoints/step-0000000010/{name}", storage.read(step_path(10, name)))
    assert [(i.step, i.status) for i in scan(storage)] == [(1_000_000_000, VERIFIED), (10, VERIFIED), (8, VERIFIED)]


class Exploit:
    def __init__(self, marker: pathlib.Path):
        self.marker = marker

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def test_decode_refuses_pickled_code(tmp_path):
    marker = tmp_path / "pwned"
    with pytest.raises(CorruptCheckpoint, match=r"not loadable as plain data: .*Unsupported global"):
        decode(encode({"payload": Exploit(marker)}))
    assert not marker.exists()
    with pytest.raises(CorruptCheckpoint, match="not loadable"):
        decode(b"not a checkpoint")
    with pytest.raises(CorruptCheckpoint, match="not a dict"):
        decode(encode([1, 2]))  # type: ignore[arg-type]


def test_select_resume_falls_back_to_the_newest_verified_and_quarantines(storage_url):
    storage = Storage.open(*storage_url)
    for step in (10, 20, 30):
        make_step(storage, step)
    write_file(storage, 40, "common.pt", b"a save that never committed")
    flip_shard_byte(storage, 30)
    lines: list[str] = []

    step, manifest = select_resume(storage, log=lines.append)

    assert (step, manifest) == (20, read_manifest(storage, 20))
    assert lines[0].startswith("skipping checkpoint step 40: incomplete (MANIFEST.json: missing")
    assert lines[1].startswith("skipping checkpoint step 30: corrupt, quarantined (rank-00001.pt: sha256 mismatch")
    statuses = {info.step: info.status for info in scan(storage)}
    assert statuses == {40: INCOMPLETE, 30: QUARANTINE, 20: VERIFIED, 10: VERIFIED}
    assert storage.exists(step_path(30, "rank-00001.pt"))  # quarantine keeps the data

    lines.clear()
    assert select_resume(storage, log=lines.append)[0] == 20
    assert lines[1].startswith("skipping checkpoint step 30: quarantined (QUARANTINED.json: rank-00001.pt: sha256")


def test_select_resume_without_a_verified_step(storage):
    assert select_resume(storage, log=print) is None
    write_file(storage, 10, "common.pt", b"x")
    assert select_resume(storage, log=lambda line: None) is None


def test_resolve_checkpoint_url(tmp_path):
    root = str(tmp_path / "run")
    storage = Storage.open(root)
    for step in (10, 20, 30):
        make_step(storage, step)
    flip_shard_byte(storage, 30)

    _, step, manifest = resolve_checkpoint_url(f"{root}/checkpoints/step-000000010/")
    assert (step, manifest["step"]) == (10, 10)
    _, step, _ = resolve_checkpoint_url(root, log=lambda line: None)
    assert step == 20
    assert not storage.exists(step_path(30, QUARANTINED))  # resolving never writes
    with pytest.raises(UserError, match=r"step-000000030 does not verify .*sha256 mismatch"):
        resolve_checkpoint_url(f"{root}/checkpoints/step-000000030")
    with pytest.raises(UserError, match=r"checkpoint .*step-000000040 does not exist: see ftrain ckpt ls .*run$"):
        resolve_checkpoint_url(f"{root}/checkpoints/step-000000040")  # moved to quarantine/, or never there
    with pytest.raises(UserError, match=r"nowhere does not exist: pass a run's storage or a step directory$"):
        resolve_checkpoint_url(str(tmp_path / "nowhere"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(UserError, match=r"no verified checkpoint under .*: pass a run's storage or a step directory$"):
        resolve_checkpoint_url(str(tmp_path / "empty"))
    for step in (10, 20):
        flip_shard_byte(storage, step)
    with pytest.raises(UserError, match=f"no verified checkpoint under {root}: see ftrain ckpt ls {root}$"):
        resolve_checkpoint_url(root, log=lambda line: None)  # steps that do not verify: ls says why


@pytest.mark.parametrize(
    ("url", "expected"),
    [
        ("runs/hc/checkpoints/step-000000120", ("runs/hc", 120)),
        ("s3://bucket/run/checkpoints/step-000000120/", ("s3://bucket/run", 120)),
        ("checkpoints/step-7", (".", 7)),
        ("/checkpoints/step-7", ("/", 7)),
        ("s3://bucket/run", ("s3://bucket/run", None)),
        ("s3://bucket/mycheckpoints/step-1", ("s3://bucket/mycheckpoints/step-1", None)),
    ],
)
def test_parse_checkpoint_url(url, expected):
    assert parse_checkpoint_url(url) == expected


def infos(verified=(), incomplete=(), corrupt=(), quarantined=(), metrics=None) -> list[StepInfo]:
    metrics = metrics or {}
    steps = [StepInfo(s, VERIFIED, manifest={"metrics": {"mean_return": metrics.get(s, 0.0)}}) for s in verified]
    steps += [StepInfo(s, INCOMPLETE) for s in incomplete]
    steps += [StepInfo(s, CORRUPT) for s in corrupt] + [StepInfo(s, QUARANTINE) for s in quarantined]
    return steps


SIX = (10, 20, 30, 40, 50, 60)


@pytest.mark.parametrize(
    ("steps", "rules", "deleted"),
    [
        (infos(SIX), {"keep_last": 3}, [30, 20, 10]),
        (infos(SIX, metrics={20: 9.0, 40: 5.0}), {"keep_last": 1, "keep_best": 2}, [50, 30, 10]),
        (infos(SIX), {"keep_last": 1, "keep_every": 20}, [50, 30, 10]),
        (infos(SIX), {"keep_last": 2, "pinned": [10]}, [40, 30, 20]),
        (infos(SIX, metrics={10: 99.0}), {"keep_last": 0, "keep_best": 1}, [50, 40, 30, 20]),  # never the newest
        (infos((10, 20), incomplete=(5, 15, 25)), {"keep_last": 1}, [15, 10, 5]),  # 25 may be a save in flight
        (infos((10, 20), corrupt=(15,), quarantined=(25, 5)), {"keep_last": 1}, [10]),
        (infos((10, 20), corrupt=(15,), quarantined=(25, 5)), {"keep_last": 1, "drop_bad": True}, [25, 15, 10, 5]),
        (infos(incomplete=(5, 15), quarantined=(25,)), {"keep_last": 1}, []),  # nothing committed: touch nothing
        (infos(SIX, metrics={10: float("nan")}), {"keep_last": 1, "keep_best": 1}, [50, 40, 30, 20, 10]),
    ],
)
def test_retention_plan(steps, rules, deleted):
    assert retention_plan(steps, **rules) == deleted


class RecordingStorage(Storage):
    """Real local storage that also records the order of deletes."""

    deleted: list[str]

    def delete(self, rel: str) -> None:
        self.deleted.append(rel.rpartition("/")[2])
        super().delete(rel)

    def delete_tree(self, rel: str) -> None:
        self.deleted.append(f"tree of {sorted(self.list_files(rel))}")
        super().delete_tree(rel)

    def delete_files(self, rel: str, names) -> bool:
        names = sorted(names)
        self.deleted.append(f"files {names}")
        return super().delete_files(rel, names)

    def _list(self, rel: str) -> dict[str, dict]:
        self.listings = getattr(self, "listings", 0) + 1
        return super()._list(rel)


def test_delete_step_removes_the_manifest_first_then_the_rest(tmp_path):
    storage = RecordingStorage.open(str(tmp_path / "run"))
    storage.deleted = []
    make_step(storage, 10)
    make_step(storage, 20)
    delete_step(storage, 10)
    assert storage.deleted == [MANIFEST, "tree of ['common.pt', 'rank-00000.pt', 'rank-00001.pt']"]
    assert storage.list_dirs(CHECKPOINTS) == ["step-000000020"]
    assert verify_step(storage, 20).ok


def test_delete_step_by_its_manifests_files_needs_no_listing_unless_something_else_is_there(tmp_path):
    storage = RecordingStorage.open(str(tmp_path / "run"))
    storage.deleted = []
    files = sorted(make_step(storage, 10)["files"])
    make_step(storage, 20)
    storage.write_replace(f"{step_dir(20)}/stray.txt", b"left by someone")
    infos = {info.step: info for info in scan(storage)}
    assert (infos[10].strays, sorted(infos[10].files)) == (False, files)
    assert (infos[20].strays, infos[20].files) == (True, [])  # its tree is deleted, strays and all
    listings = storage.listings
    delete_step(storage, 10, infos[10].files)
    assert storage.listings == listings
    delete_step(storage, 20, files)  # told only the manifest's files: the stray is found and deleted too
    assert storage.deleted == [MANIFEST, f"files {files}", MANIFEST, f"files {files}", "tree of ['stray.txt']"]
    assert storage.list_dirs(CHECKPOINTS) == []


def test_delete_step_by_files_on_every_backend(storage_url):
    storage = Storage.open(*storage_url)
    files = list(make_step(storage, 10)["files"])
    make_step(storage, 20)
    delete_step(storage, 10, files)
    assert [info.step for info in scan(storage)] == [20]
    assert verify_step(storage, 20).ok


def test_clear_newer_deletes_abandoned_steps_and_sets_bad_ones_aside_intact(storage):
    make_step(storage, 10)
    write_file(storage, 20, "rank-00000.pt", b"killed mid-save")
    make_step(storage, 30)
    quarantine(storage, 30, "test")
    make_step(storage, 40)
    truncate_shard(storage, 40)
    quarantined = {name: storage.read(step_path(30, name)) for name in storage.list_files(step_dir(30))}
    lines: list[str] = []
    clear_newer(storage, 10, log=lines.append)
    assert len(lines) == 3 and "step 40 (corrupt) moved to" in lines[0]
    assert lines[0].endswith(": newer than step 10, which this run goes on from"), lines  # not "saves it again"
    assert "step 30 (quarantined) moved to" in lines[1] and "step 20 (incomplete)" in lines[2]
    assert [i.step for i in scan(storage)] == [10]
    aside = dict(set_aside_steps(storage))
    assert set(aside) == {"step-000000030", "step-000000040"} and aside["step-000000030"] == "test"
    assert "size mismatch" in aside["step-000000040"]  # quarantined with its reason before it moved
    assert {name: storage.read(f"{ASIDE}/step-000000030/{name}") for name in quarantined} == quarantined

    make_step(storage, 30)  # the resumed run saves step 30 again; a second bad 30 goes next to the first
    quarantine(storage, 30, "again")
    clear_newer(storage, 10)
    assert dict(set_aside_steps(storage))["step-000000030.1"] == "again"
    make_step(storage, 20)
    with pytest.raises(UserError, match="verified checkpoint step 20"):
        clear_newer(storage, 10)
    assert verify_step(storage, 20).ok


def test_on_a_shared_file_system_a_young_incomplete_step_is_set_aside_not_deleted(tmp_path):
    """On a network or FUSE file system, another host's manifest may reach this host's listings late (NFS caches
    lookups): an incomplete step newer than the resume step is deleted only once nothing was written to it for
    ``ABANDONED_AFTER`` seconds; a younger one is set aside whole (``quarantine/``) with the reason. A FUSE mount of
    the test's own stands for NFS; on a local disk both are deleted (the test above)."""
    assert not Storage.open(str(tmp_path / "local")).lists_late
    with failing_mount(tmp_path / "fuse") as mount:
        storage = Storage.open(str(mount.path / "run"))
        assert storage.lists_late
        make_step(storage, 10)
        write_file(storage, 20, "rank-00000.pt", b"a save in flight, or killed mid-save a moment ago")
        write_file(storage, 30, "rank-00000.pt", b"killed mid-save long ago")
        old = time.time() - ABANDONED_AFTER - 60
        for path in (mount.path.parent / "backing" / "run" / "checkpoints" / "step-000000030").iterdir():
            os.utime(path, (old, old))
        lines: list[str] = []
        clear_newer(storage, 10, log=lines.append)
        assert [info.step for info in scan(storage)] == [10]
        assert "checkpoint step 30 (incomplete)" in lines[0] and "deleting" in lines[0], lines
        assert "checkpoint step 20 (incomplete, last written" in lines[1] and "moved to" in lines[1], lines
        (aside, reason), *_ = set_aside_steps(storage)
        assert aside == "step-000000020" and "may lag" in reason
        assert storage.read(f"{ASIDE}/step-000000020/rank-00000.pt").startswith(b"a save in flight")


def test_unquarantine_lifts_only_a_step_that_verifies(storage):
    make_step(storage, 10)
    make_step(storage, 20)
    quarantine(storage, 10, "a load error of an older ftrain")
    quarantine(storage, 20, "bit rot")
    flip_shard_byte(storage, 20)
    assert unquarantine(storage, 10).ok
    assert not unquarantine(storage, 20).ok
    assert {i.step: i.status for i in scan(storage)} == {20: QUARANTINE, 10: VERIFIED}


def test_a_step_whose_manifest_a_lagging_listing_lacks_is_not_taken_for_abandoned(s3_url):
    """A shared filesystem that caches directories (NFS across nodes) lists a step without the manifest that came
    after; here S3 read through fsspec's listings cache does the same. Starting from step 20, the steps past it are
    cleared: step 40 must not be deleted as never committed. Its manifest is read directly, and it is a verified step
    of another history (refused, nothing touched)."""
    url, options = s3_url
    writer, reader = Storage.open(url, options), Storage.open(url, {**options, "use_listings_cache": True})
    make_step(writer, 20)
    files = {name: write_file(writer, 40, name, encode({"step": 40})) for name in ("common.pt", "rank-00000.pt")}
    assert [info.step for info in scan(reader)] == [40, 20]
    assert MANIFEST not in reader.list_files(step_dir(40))  # the reader lists step 40 before it is committed
    commit(writer, 40, files, {"iteration": 40, "world_size": 1, "metrics": {}})
    assert MANIFEST not in reader.list_files(step_dir(40))  # and its listing lags behind
    assert {info.step: info.status for info in scan(reader)} == {40: VERIFIED, 20: VERIFIED}
    with pytest.raises(UserError, match="already holds verified checkpoint step 40"):
        clear_newer(reader, 20, log=print)
    assert verify_step(writer, 40).ok


def test_recorded_metrics_are_strict_json_without_timing() -> None:
    """What manifests and policy lineages record: a metric not measured yet (NaN, the mean return before any episode
    ended) is null, since JSON has no NaN (a snapshot's lineage.json held a bare NaN, which jq refuses)."""
    metrics = {"mean_return": float("nan"), "loss/value": 0.5, "iteration_time": 1.2, "time/env_ms": 3.0, "x": -1e300}
    recorded = recorded_metrics(metrics)
    assert recorded == {"mean_return": None, "loss/value": 0.5, "x": -1e300}
    assert json.loads(json.dumps(recorded, allow_nan=False)) == recorded
    assert recorded_metrics({"inf": float("inf")}) == {"inf": None}
