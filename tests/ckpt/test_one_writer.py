"""Every write and every delete of a run's storage goes through the holder's check (``fence.guarded``), on a local
directory and on a real S3 API server: for each kind of write, a holder of an older generation that tries it after
the lease moved on is refused and nothing is written or deleted, while the current holder's same write goes through.
Lineage (``lineage.py``): what resume and ``ftrain ckpt verify`` make of forked and superseded histories."""

from __future__ import annotations

import json
import os
import random
import re
import subprocess

import pytest
import torch

from ftrain.ckpt import commands, lineage
from ftrain.ckpt.fence import Fence
from ftrain.ckpt.format import commit, encode, step_dir, write_file
from ftrain.ckpt.lease import Lease, LeaseLost
from ftrain.ckpt.retention import delete_step
from ftrain.ckpt.save import Result, StepWriter
from ftrain.ckpt.steps import (
    ASIDE,
    check_output,
    check_storage_place,
    clear_newer,
    quarantine,
    scan,
    select_resume,
    set_aside,
    superseded_reason,
)
from ftrain.ckpt.storage import Storage
from ftrain.comm.group import RankInfo
from ftrain.config import CheckpointConfig
from ftrain.errors import UserError
from ftrain.identity import ATTEMPT_ENV, GENERATION_ENV, RUN_ID_ENV, Identity
from ftrain.policy.snapshots import PoliciesView
from ftrain.policy.snapshots import prune as prune_snapshots

from helpers import child_env, make_step, supervise_command, train_command


@pytest.fixture(params=["local", "s3"])
def where(request, tmp_path) -> tuple[str, dict | None]:
    """The URL and storage options of a fresh run storage."""
    return (str(tmp_path / "run"), None) if request.param == "local" else request.getfixturevalue("s3_url")


@pytest.fixture
def storage(where) -> Storage:
    return Storage.open(*where)


def everything(storage: Storage) -> dict[str, bytes]:
    """Every object under the storage but the lease's own files, with its bytes."""
    root = storage.root
    paths = storage.fs.find(root)
    kept = [path for path in paths if not path.rpartition("/")[2].startswith(("LEASE.json", "FENCE.json"))]
    return {path.removeprefix(root): storage.fs.cat_file(path) for path in kept}


@pytest.fixture
def moved_on(storage):
    """A storage with history (steps 10 and 20, an abandoned step 30, snapshots 10 and 20) written by run A at
    generation 1, whose lease run B then took at generation 2: A's and B's guarded views of it."""
    a = Lease(storage, "run-a", print)
    a.acquire()
    for step in (10, 20):
        make_step(storage, step, world_size=1)
        snapshots = PoliciesView(storage)
        commit(snapshots, step, {"actor.pt": write_file(snapshots, step, "actor.pt", b"actor")}, {})
    write_file(storage, 30, "rank-00000.pt", b"cut short")  # no manifest: abandoned
    a.release()
    b = Lease(storage, "run-b", print)
    b.acquire()
    assert b.generation == 2
    stale = storage.guarded(Fence(storage, Identity("run-a", 1)).holding)
    current = storage.guarded(Fence(storage, Identity("run-b", 2)).holding)
    return stale, current


WRITES = {
    "retention": lambda s: delete_step(s, 10),
    "quarantine": lambda s: quarantine(s, 20, "a test"),
    "start-up clean-up": lambda s: clear_newer(s, 20, print),
    "set aside": lambda s: set_aside(s, next(info for info in scan(s) if info.step == 10)),
    "snapshot write": lambda s: write_file(PoliciesView(s), 40, "actor.pt", b"newer actor"),
    "snapshot prune": lambda s: prune_snapshots(PoliciesView(s), keep_last=1),
    "snapshot start-up deletion": lambda s: delete_step(PoliciesView(s), 20),
    "shard": lambda s: write_file(s, 40, "rank-00000.pt", encode({"x": torch.ones(2)})),
    "manifest": lambda s: commit(s, 30, {}, {}, check_present=False),
}


@pytest.mark.parametrize("kind", list(WRITES))
def test_a_holder_of_an_older_generation_writes_and_deletes_nothing(moved_on, storage, kind):
    stale, current = moved_on
    before = everything(storage)
    with pytest.raises(LeaseLost, match=re.escape("taken by run run-b (generation 2; this run's is 1)")):
        WRITES[kind](stale)
    assert everything(storage) == before, f"{kind}: the stale holder changed the storage"
    WRITES[kind](current)  # the holder's own write of the same kind goes through: the check is no blanket refusal
    assert everything(storage) != before, f"{kind}: the current holder's write must land"


def test_a_save_of_a_holder_of_an_older_generation_is_refused_before_its_shards(moved_on, storage, monkeypatch):
    """The real save path (a one-rank world): its shard write is refused, so not even an uncommitted file lands."""
    before = everything(storage)
    for name, value in Identity("run-a", 1).env().items():
        monkeypatch.setenv(name, value)
    lines: list[str] = []
    writer = StepWriter(storage, CheckpointConfig(), RankInfo(0, 1, 0), None, lines.append)
    state = {"ftrain": {}, "actor_state_dict": {"w": torch.ones(3)}}
    outcome = writer.save(40, {"common.pt": state, "rank-00000.pt": {"rng": torch.ones(2)}}, {"iteration": 40}, False)
    assert outcome.result is Result.LEASE_LOST and "this run lost the storage" in outcome.detail
    assert everything(storage) == before
    assert lines == [f"checkpoint step 40 refused: {outcome.detail}"]


def save(storage: Storage, monkeypatch, identity: Identity, step: int, parent: dict | None = None) -> dict:
    """One real save of a one-rank world of ``identity`` continuing ``parent``: its manifest."""
    for name in (RUN_ID_ENV, GENERATION_ENV, ATTEMPT_ENV):
        monkeypatch.delenv(name, raising=False)
    for name, value in identity.env().items():
        monkeypatch.setenv(name, value)
    writer = StepWriter(storage, CheckpointConfig(keep_last=100), RankInfo(0, 1, 0), None, print)
    writer.parent = parent
    state = {"ftrain": {}, "actor_state_dict": {"w": torch.full((3,), float(step))}}
    outcome = writer.save(step, {"common.pt": state, "rank-00000.pt": {}}, {"iteration": step}, False)
    assert outcome.result is Result.COMMITTED, outcome.detail
    return outcome.detail


def parent_of(manifest: dict) -> dict:
    return {"step": manifest["step"], "state_sha256": manifest["state_sha256"]}


def test_each_commit_names_its_parent_and_the_history_is_one_line(storage, monkeypatch):
    first = save(storage, monkeypatch, Identity("run-a", 1), 10)
    second = save(storage, monkeypatch, Identity("run-a", 1), 20, parent_of(first))
    third = save(storage, monkeypatch, Identity("run-b", 2), 30, parent_of(second))  # the next run resumed at 20
    assert (first["parent"], second["parent"], third["parent"]) == (None, parent_of(first), parent_of(second))
    delete_step(storage, 20)  # retention: a parent gone is passed over
    past = lineage.history(scan(storage))
    assert (past.line, past.superseded, past.forks) == ([30, 10], [], [])
    assert select_resume(storage)[0] == 30


def test_a_commit_that_landed_after_its_lease_moved_on_is_superseded_and_set_aside(storage, where, monkeypatch, capsys):
    """Run A committed 20 from 10 after run B (a newer generation) had resumed from 10 (the one-request window of an
    object store): B's line wins; resume passes over A's step and the start-up clean-up sets it aside."""
    ten = save(storage, monkeypatch, Identity("run-a", 1), 10)
    save(storage, monkeypatch, Identity("run-a", 1), 20, parent_of(ten))  # the late commit
    save(storage, monkeypatch, Identity("run-b", 2), 15, parent_of(ten))
    past = lineage.history(scan(storage))
    assert (past.line, past.superseded, past.forks) == ([15, 10], [20], [])
    lines: list[str] = []
    assert select_resume(storage, log=lines.append)[0] == 15
    assert lines == [f"skipping checkpoint step 20: {lineage_reason(storage, 20)}"]
    assert commands.verify(*where) == 0
    out = capsys.readouterr().out
    assert "step 20: superseded: committed by generation 1 after generation 2 went on" in out
    assert "one history: 2 steps on one line of descent, 1 superseded" in out
    clear_newer(storage, 15, print)
    assert [info.step for info in scan(storage)] == [15, 10] and storage.list_dirs(ASIDE) == [step_dir(20)[12:]]


def lineage_reason(storage: Storage, step: int) -> str:
    infos = scan(storage)
    return superseded_reason(next(i for i in infos if i.step == step), lineage.history(infos))


def test_a_fork_of_one_generation_is_refused_until_one_line_is_kept(storage, where, monkeypatch, capsys):
    """Two processes of one generation wrote one storage as one run (what the shared run id ``none`` did): resume
    refuses in one line that says how to pick a branch; ``ftrain ckpt prune --keep-line`` sets the other aside."""
    same = Identity("none", 1)
    ten = save(storage, monkeypatch, same, 10)
    twenty = save(storage, monkeypatch, same, 20, parent_of(ten))
    save(storage, monkeypatch, same, 30, parent_of(twenty))
    save(storage, monkeypatch, same, 25, parent_of(ten))  # the other process's branch from 10
    with pytest.raises(UserError) as refused:
        select_resume(storage)
    message = str(refused.value)
    assert "holds two histories of generation 1: steps 30, 20, 10 and steps 25" in message
    assert f"with ftrain ckpt prune {storage.url} --keep-line STEP (the" in message and "\n" not in message
    assert commands.verify(*where) == 1 and "FORKED: " in capsys.readouterr().out
    for name in (RUN_ID_ENV, GENERATION_ENV, ATTEMPT_ENV):
        monkeypatch.delenv(name, raising=False)
    assert commands.keep_line(where[0], 25, where[1]) == 0
    assert [info.step for info in scan(storage) if info.manifest] == [25, 10]
    assert select_resume(storage)[0] == 25
    aside = json.loads(storage.read(f"{ASIDE}/{step_dir(30)[12:]}/QUARANTINED.json"))
    assert "off the line kept by ftrain ckpt prune --keep-line 25" in aside["reason"]


def test_a_lease_record_deleted_by_hand_starts_after_the_newest_generation_that_committed(storage, monkeypatch):
    """One node keeps no fence record: the next holder takes its generation from the newest manifest, so its commits
    are not taken for an older generation's and superseded."""
    for run in ("run-a", "run-b", "run-c"):
        lease = Lease(storage, run, print)
        lease.acquire()
        lease.release()
    assert lease.generation == 3
    save(storage, monkeypatch, Identity("run-c", 3), 10)
    storage.delete("LEASE.json")
    after = Lease(storage, "run-d", print)
    after.acquire()
    assert after.generation == 4
    save(storage, monkeypatch, Identity("run-d", 4), 20, {"step": 10, "state_sha256": None})
    assert lineage.history(scan(storage)).line == [20, 10]


INSIDE_A_STEP = [
    ("{run}/checkpoints/step-000000004", "{run}/checkpoints/step-000000004", True),
    ("{run}/checkpoints/step-000000004/sub/", "{run}/checkpoints/step-000000004", True),
    ("file://{run}/checkpoints/step-000000004", "file://{run}/checkpoints/step-000000004", True),
    ("{run}/quarantine/step-000000004/x", "{run}/quarantine/step-000000004", False),
    ("{run}/quarantine/step-000000004.1", "{run}/quarantine/step-000000004.1", False),  # set aside a second time
    ("{run}/policies/step-000000004/mine", "{run}/policies/step-000000004", False),  # a policy snapshot
    ("s3://bucket/exp/checkpoints/step-7", "s3://bucket/exp/checkpoints/step-7", True),
]


@pytest.mark.parametrize(("url", "step", "resumable"), INSIDE_A_STEP)
def test_a_storage_inside_a_step_of_another_storage_is_refused(tmp_path, url, step, resumable) -> None:
    """That run's retention and clean-up would delete what a run there writes, while it reports success. A local step
    that is there is named to train on from (``resume=``), one that is not is not."""
    run = tmp_path / "run"
    make_step(Storage.open(str(run)), 4)
    with pytest.raises(UserError) as refused:
        check_storage_place(url.format(run=run))
    line = str(refused.value)
    place = "is" if url == step else f"is inside {step.format(run=run)},"  # the step itself: named once
    assert line.startswith(f"storage {url.format(run=run)} {place} a step of another run's storage"), line
    assert ("resume=" in line) == resumable, line
    if resumable and not url.startswith("s3:"):
        with pytest.raises(UserError, match=rf"step-000000005 does not exist; its steps: ftrain ckpt ls {run}\)$"):
            check_storage_place(url.format(run=run).replace("step-000000004", "step-000000005"))
    named_alike = (f"{run}/checkpoints", f"{run}/steps/step-000000004", "s3://bucket/checkpoints/run")
    for own in (run, *named_alike, "s3://checkpoints/step-1", "memory://policies/step-3/run"):  # nothing above a bucket
        check_storage_place(str(own))  # a directory named checkpoints, or a step of nothing, is a storage's own


def test_generated_places_inside_a_step_are_refused_and_others_taken_with_no_credential_shown() -> None:
    """Generated URLs (roots, step parents, step names, depths, credentials): refused exactly where a step of a
    storage with something above its parent encloses them, and the line never shows a credential."""
    draw = random.Random(random.SystemRandom().randrange(2**31))
    roots = ["run", "/data/run", "s3://AKIA1:S3CR3T@bucket/exp", "abfs://box@acct/x?sig=S3CR3T", "file:///r", "."]
    parents = ["checkpoints", "quarantine", "policies", "steps", "check"]
    names = ["step-000000012", "step-7.2", "step-", "steps-1", "step-1x"]
    count = refused = 0
    for _ in range(500):
        root, parent, name = draw.choice(roots), draw.choice(parents), draw.choice(names)
        base, _, query = root.partition("?")
        tail = "/".join(draw.choice(["a", "b", "c"]) for _ in range(draw.randrange(3)))
        url = "/".join(filter(None, [base, parent, name, tail])) + (f"?{query}" if query else "")
        inside = parent in ("checkpoints", "quarantine", "policies") and re.fullmatch(r"step-\d+(\.\d+)?", name)
        count += 1
        try:
            check_storage_place(url)
        except UserError as error:
            refused += 1
            assert inside, url
            assert "S3CR3T" not in str(error) and "AKIA1:" not in str(error), str(error)
        else:
            assert not inside, url
    print(f"{count} generated places checked, {refused} refused")
    assert 0 < refused < count


def test_where_a_local_storage_really_goes_decides_not_its_spelling(tmp_path, monkeypatch) -> None:
    """A symbolic link into a step is inside that step (a run trained into another run's step through one); a path
    through a step and back out (``step-N/../..``) is the storage it reaches, not inside the step it names."""
    run = tmp_path / "run"
    make_step(Storage.open(str(run)), 4)
    step = run / "checkpoints" / "step-000000004"
    (tmp_path / "link").symlink_to(step)
    (tmp_path / "to-run").symlink_to(run)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "linked-run").mkdir()  # a run whose checkpoints/ is on another disk, linked
    (tmp_path / "disk").mkdir()
    (tmp_path / "disk" / "step-000000004").mkdir()
    (tmp_path / "linked-run" / "checkpoints").symlink_to(tmp_path / "disk")
    inside_by_name = "linked-run/checkpoints/step-000000004/new"
    with pytest.raises(UserError, match=" is inside linked-run/checkpoints/step-000000004, a step of another run's"):
        check_storage_place(inside_by_name)  # its real path names no checkpoints/ of linked-run: its name does
    for refused in ("link", f"{tmp_path}/link/sub", "to-run/checkpoints/step-000000004", f"{step}/x/.."):
        with pytest.raises(UserError, match=f" is (inside {re.escape(str(step))}, )?a step of another run's storage"):
            check_storage_place(refused)
    for taken in (f"{step}/../..", "to-run", "link/../.."):
        check_storage_place(taken)
    print("8 spellings decided by their name and where they go")


@pytest.mark.parametrize("command", [train_command, supervise_command])
def test_train_and_supervise_refuse_a_storage_or_logs_inside_a_step_before_they_touch_it(tmp_path, command) -> None:
    """A log directory there (``log_dir=``, another storage's run) was taken: that run's retention deleted its
    config, metrics and lock with the step, in silence."""
    run = Storage.open(str(tmp_path / "run"))
    make_step(run, 4)
    inside = tmp_path / "run" / "checkpoints" / "step-000000004"
    before = sorted(path.name for path in inside.iterdir())
    result = subprocess.run(command(inside), cwd=tmp_path, env=child_env(), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"ftrain: error: storage {inside} is a step of another run's storage, which that run may "
        f"delete: pass a directory of its own (to train on from that step: resume={inside})"
    ], result.stderr
    logs = command(tmp_path / "other", f"log_dir={inside / 'logs'}")
    result = subprocess.run(logs, cwd=tmp_path, env=child_env(), capture_output=True, text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [
        f"ftrain: error: log_dir {inside / 'logs'} lies inside {inside}, a step of a run's storage: a file written "
        "there replaces the step's own or is deleted with it: pass log_dir a path outside the storage's steps"
    ], result.stderr
    assert sorted(path.name for path in inside.iterdir()) == before and not (tmp_path / "other").exists()
    assert [info.status for info in scan(run, full=True)] == ["verified"]


def test_a_spool_and_a_storage_are_never_one_directory(tmp_path) -> None:
    """A run on S3 keeps its spool in ``<log_dir>/spool`` and empties it when it starts afresh: a local run there lost
    every step, in silence, whichever started first. Both orders are refused in one line with exit 2, nothing
    written or deleted; a directory named spool in no log directory, or a spool switched off, is taken."""
    from ftrain.ckpt.spool import check_place
    from ftrain.config import load_config

    logs = tmp_path / "logs"
    logs.mkdir()
    (logs / "storage.txt").write_text("s3://bucket/run\n")
    spool = logs / "spool"
    result = subprocess.run(
        train_command(spool), cwd=tmp_path, env=child_env(), capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2 and result.stderr.strip().splitlines() == [
        f"ftrain: error: storage {spool} is the spool of the run on s3://bucket/run, whose log directory is {logs}: "
        "that run empties it: pass a directory of its own"
    ], result.stderr
    assert not spool.exists()
    check_place(load_config(None, [f"storage.url={tmp_path / 'plain' / 'spool'}"]))
    (tmp_path / "local").mkdir()  # the log directory of a run on a local storage, which keeps no spool
    (tmp_path / "local" / "storage.txt").write_text(f"{tmp_path / 'local'}\n")
    check_place(load_config(None, [f"storage.url={tmp_path / 'local' / 'spool'}"]))
    make_step(Storage.open(str(spool)), 4)  # a local run there, then one on S3 whose log directory is above it
    (spool / "LEASE.json").write_text("{}")
    remote = ["storage.url=s3://bucket/other", f"log_dir={logs}"]
    with pytest.raises(UserError, match=rf"would keep this run's spool in {re.escape(str(spool))}, which is the "):
        check_place(load_config(None, remote))
    check_place(load_config(None, [*remote, "checkpoint.spool=false"]))
    assert [info.status for info in scan(Storage.open(str(spool)), full=True)] == ["verified"]


def test_a_storage_in_a_runs_quarantine_is_refused_however_it_is_spelt(tmp_path, monkeypatch) -> None:
    """A run's ``quarantine/`` is deleted whole by ``prune --drop-bad`` (every directory there is a step set aside,
    whatever its name): a storage there, or an exported file, was taken, and that prune deleted the run trained
    there. Generated places in and around it: refused where they lie inside a run's quarantine/, taken elsewhere
    (a directory named quarantine of no run), and a train there is one line, exit 2, with nothing written."""
    run = tmp_path / "run"
    make_step(Storage.open(str(run)), 2)
    (tmp_path / "plain" / ASIDE).mkdir(parents=True)  # named so, but no run's
    monkeypatch.chdir(tmp_path)
    seed = random.SystemRandom().randrange(2**31)
    draw = random.Random(seed)
    count = refused = 0
    for _ in range(200):
        base = draw.choice(["run", str(run), f"file://{run}", "plain", "./run", "run/../run"])
        tail = "/".join(draw.choice(["a", "step-x", ASIDE]) for _ in range(draw.randrange(3)))
        below = draw.choice([ASIDE, "other"])  # a quarantine/ deeper down lies in no run's storage
        place = "/".join(filter(None, [base, below, tail])) + draw.choice(["", "/"])
        inside = below == ASIDE and base != "plain"
        count += 1
        try:
            check_storage_place(place)
        except UserError as error:
            refused += 1
            assert inside and f"is the {ASIDE}/ of the run in " in str(error), place
        else:
            assert not inside, place
    print(f"{count} generated places checked (seed {seed}), {refused} refused")
    assert 0 < refused < count
    check_storage_place(f"file://{run}/{ASIDE}/..")  # the run itself, spelt through its quarantine/
    with pytest.raises(UserError, match=f"is the {ASIDE}/ of the run in {run}, "):
        check_storage_place(f"file://{run}/{ASIDE}/a/..")
    result = subprocess.run(train_command(run / ASIDE, "iterations=2"), env=child_env(), capture_output=True, text=True)
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "ftrain ckpt prune --drop-bad deletes all of it: pass a directory of its own" in result.stderr
    assert not (run / ASIDE).exists() and sorted(os.listdir(run / "checkpoints")) == ["step-000000002"]
    with pytest.raises(UserError, match=rf"^-o {run}/{ASIDE}/p.onnx lies inside the {ASIDE}/ of the run in {run}: "):
        check_output(run / ASIDE / "p.onnx", "-o")


def test_a_runs_checkpoints_directory_passed_as_a_storage_is_refused_before_anything_is_written(tmp_path) -> None:
    """``--storage <run>/checkpoints`` started a fresh run beside that run's steps (lease, logs, a nested
    ``checkpoints/``); now one line, exit 2, and the directory as it was."""
    run = tmp_path / "run"
    for step in (2, 4):
        make_step(Storage.open(str(run)), step)
    before = sorted(os.listdir(run / "checkpoints"))
    train = train_command(run / "checkpoints", "iterations=2", f"log_dir={tmp_path / 'logs'}")
    for command in (train, supervise_command(run / "checkpoints")):  # the supervisor's logs go to the storage
        result = subprocess.run(command, env=child_env(), capture_output=True, text=True)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert result.stderr.strip() == (
            f"ftrain: error: storage {run / 'checkpoints'} holds step directories itself (step-000000002, "
            "step-000000004): it is the checkpoints directory of a run, whose storage is the directory above it: "
            "pass that to resume it, or a directory of its own"
        )
        assert sorted(os.listdir(run / "checkpoints")) == before  # no lease, no log (the supervisor's warm pool)
