import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ftrain.ckpt import commands as ckpt_commands
from ftrain.ckpt.format import encode, read_manifest, step_dir, write_file
from ftrain.ckpt.steps import ABANDONED_AFTER, resolve_checkpoint_url, scan
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError

from helpers import (
    REPO,
    flip_shard_byte,
    kill_tree,
    make_step,
    manifests,
    on_a_terminal,
    start_train,
    truncate_shard,
    wait_for,
)


def build_tree(storage: Storage) -> None:
    """Verified 10, 20, 30; corrupt 25 (truncated shard); incomplete 40 (a save in flight)."""
    for step in (10, 20, 25, 30):
        make_step(storage, step, metrics={"mean_return": float(step), "mean_length": 1000})
    truncate_shard(storage, 25)
    write_file(storage, 40, "common.pt", b"half a save")


@pytest.fixture
def run(tmp_path) -> str:
    url = str(tmp_path / "run")
    build_tree(Storage.open(url))
    return url


def lines_by_step(text: str) -> dict[int, str]:
    """The table's row of each step, with the indented lines of problems under it (not the lines after the table)."""
    rows: dict[int, str] = {}
    for line in text.splitlines()[1:]:
        if line.split()[0].isdigit():
            step = int(line.split()[0])
            rows[step] = line
        elif line.startswith(" "):
            rows[step] += "\n" + line
    return rows


def test_ls_is_a_table_that_fits_a_terminal_and_marks_what_retention_keeps(run, capsys):
    make_step(Storage.open(run), 50, metrics={"mean_return": 5.0, "eval_return": None})
    assert ckpt_commands.ls(run) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == (
        "     step  status            size  created (UTC)     mean_return  eval_return  kept as"
    )
    assert max(len(line) for line in out.splitlines()) <= ckpt_commands.WIDTH
    assert "None" not in out
    rows = lines_by_step(out)
    assert list(rows) == [50, 40, 30, 25, 20, 10]
    assert rows[50].split()[1] == "committed" and rows[50].endswith("5.00            -  newest")
    assert rows[30].split()[1] == "committed" and rows[30].endswith("30.00            -  best")  # keep_best 1
    assert rows[30].split()[3] == "KiB" and re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d", " ".join(rows[30].split()[4:6]))
    assert rows[20].endswith("20.00            -")  # kept by nothing but keep_last
    assert rows[25].split()[1] == "corrupt" and "\n           rank-00001.pt: size mismatch" in rows[25]
    assert rows[40].split()[1] == "incomplete" and "MANIFEST.json: missing" in rows[40]


def test_verify_a_run_and_single_steps(run, capsys):
    assert ckpt_commands.verify(run) == 1
    out = capsys.readouterr().out
    assert "step 30: ok" in out and "step 25: FAILED" in out
    assert "step 40: incomplete (never committed: no manifest; last written " in out
    assert "checkpoints/step-000000025/rank-00001.pt: size mismatch" in out
    assert out.splitlines()[-2] == "one history: 3 steps on one line of descent, 0 superseded"
    assert out.splitlines()[-1] == "3 of 4 committed steps verified; 1 incomplete (never committed)"

    assert ckpt_commands.verify(f"{run}/checkpoints/step-000000020") == 0
    assert capsys.readouterr().out.splitlines() == ["step 20: ok", "1 of 1 committed step verified"]

    assert ckpt_commands.verify(f"{run}/checkpoints/step-000000040") == 1  # named, and never committed
    assert capsys.readouterr().out.splitlines()[-1] == "0 of 0 committed steps verified; 1 incomplete (never committed)"

    flip_shard_byte(Storage.open(run), 20)
    assert ckpt_commands.verify(f"{run}/checkpoints/step-000000020") == 1
    assert "checkpoints/step-000000020/rank-00001.pt: sha256 mismatch" in capsys.readouterr().out


def test_a_committed_step_whose_hash_fails_is_committed_to_every_command_not_verified(run, capsys):
    """``verify`` reads the SHA-256s, the other commands a step's manifest and sizes: a bit-rotted step that ``verify``
    fails is "committed" to them, never "verified" (a probe read "is verified, not quarantined" beside FAILED)."""
    flip_shard_byte(Storage.open(run), 30)
    assert ckpt_commands.verify(f"{run}/checkpoints/step-000000030") == 1
    assert "step 30: FAILED" in capsys.readouterr().out
    assert ckpt_commands.ls(run) == 0
    out = capsys.readouterr().out
    assert lines_by_step(out)[30].split()[1] == "committed"
    said = "committed: by its manifest and file sizes; ftrain ckpt verify (the same URL) reads every byte"
    assert out.splitlines()[-1] == said, out  # as prune and resume read it: corrupt
    with pytest.raises(UserError, match=r"step-000000030 is committed, not quarantined: nothing to lift$"):
        ckpt_commands.unquarantine(f"{run}/checkpoints/step-000000030")
    with pytest.raises(UserError, match=r"^step 99 is not a committed step of this storage: pick one of 30, 20, 10$"):
        ckpt_commands.keep_line(run, 99)


def test_show(run, capsys):
    assert ckpt_commands.show(f"{run}/checkpoints/step-000000020") == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].endswith("checkpoints/step-000000020 (verified)")
    assert "step: 20" in out and "  mean_return: 20.0" in out and "  common.pt " in out

    assert ckpt_commands.show(run, as_json=True) == 0  # the newest verified step
    assert json.loads(capsys.readouterr().out) == read_manifest(Storage.open(run), 30)

    assert ckpt_commands.show(f"{run}/checkpoints/step-000000025") == 0
    assert "(NOT verified: rank-00001.pt: size mismatch" in capsys.readouterr().out


def test_prune(run, capsys):
    assert ckpt_commands.prune(run, keep_last=1, dry_run=True) == 0
    out = capsys.readouterr().out
    assert (
        "would delete step 20 (committed, outside retention)" in out
        and "would delete step 10 (committed, outside retention)" in out
    )
    assert out.splitlines()[-1] == (  # by status: a probe read corrupt and incomplete steps as kept
        "would keep 1 committed step: 30; 1 incomplete left: 40 (maybe a save in flight); 1 corrupt left: 25 "
        "(--drop-bad deletes these)"
    )
    assert len(scan(Storage.open(run))) == 5

    assert ckpt_commands.prune(run, keep_last=1, pinned=[10]) == 0
    assert "deleting step 20 (committed, outside retention)" in capsys.readouterr().out
    assert [info.step for info in scan(Storage.open(run))] == [40, 30, 25, 10]

    assert ckpt_commands.prune(run, keep_last=1, drop_bad=True) == 0
    assert [info.step for info in scan(Storage.open(run))] == [40, 30]


def test_a_dry_run_of_prune_on_a_held_or_damaged_lease_says_prune_would_be_refused(run, capsys):
    """A dry run previews what prune does: beside another run's live lease it previews, then says that prune would be
    refused, with prune's exit code (it said nothing of it, and the real prune then refused; then it refused the
    preview too); a damaged LEASE.json refuses both; --force previews without the lease."""
    from ftrain.ckpt.lease import Entry, Record
    from ftrain.errors import EXIT_STORAGE_HELD
    from ftrain.procfs import Process

    storage = Storage.open(run)
    far = Process("node-far-away", 4242, 123, "another-boot-id", "pid:[1]")
    storage.write_replace("LEASE.json", Record("a-run", 3, 60.0, (Entry(far, time.time()),)).encode())
    for dry_run, refused in ((True, "would be refused now"), (False, "refused")):
        assert ckpt_commands.prune(run, keep_last=1, dry_run=dry_run) == EXIT_STORAGE_HELD
        captured = capsys.readouterr()
        assert ("would delete step 20" in captured.out) == dry_run and "deleting" not in captured.out, captured
        assert captured.err.startswith(f"ftrain: error: ckpt prune {refused}: storage "), captured
        assert "held by another run (a-run, pid 4242 on host node-far-away" in captured.err, captured.err
        assert captured.err.count("\n") == 1 and "(or pass --force to prune anyway)" in captured.err
    stale = Record("a-run", 3, 60.0, (Entry(far, time.time() - 600),))  # expired by its time: the storage's clock asked
    storage.write_replace("LEASE.json", stale.encode())
    os.utime(storage.fs._strip_protocol(f"{run}/LEASE.json"), (time.time() - 600, time.time() - 600))

    def read_only(path: str, data: bytes) -> None:  # a read-only mount: the clock file cannot be written
        raise OSError(30, "Read-only file system", path)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Storage, "write_replace", lambda self, rel, data: read_only(rel, data))
        assert ckpt_commands.prune(run, keep_last=1, dry_run=True) == 0  # previews; it wrote nothing
    assert "would delete step 20" in capsys.readouterr().out
    storage.write_replace("LEASE.json", b'{"run_id": "x", "generation": "1", "ttl": 60, "holders": []}')
    before = sorted(storage.fs.find(storage.root))
    for preview in (
        lambda: ckpt_commands.prune(run, keep_last=1, dry_run=True),
        lambda: ckpt_commands.keep_line(run, 30, dry_run=True),
        lambda: ckpt_commands.prune(run, keep_last=1),
    ):
        with pytest.raises(UserError, match=r"LEASE.json is not a lease ftrain can read \(generation: '1' is not"):
            preview()
    assert ckpt_commands.prune(run, keep_last=1, dry_run=True, force=True) == 0
    assert "would delete step 20" in capsys.readouterr().out
    assert sorted(storage.fs.find(storage.root)) == before


def test_prune_keeps_by_the_runs_own_settings_unless_told_otherwise_and_refuses_a_metric_no_step_records(
    tmp_path, capsys
):
    url = str(tmp_path / "run")
    own = {"checkpoint": {"keep_last": 3, "keep_best": 1, "best_metric": "eval_return", "pinned": [10]}}
    for step, score in ((10, 1.0), (20, 9.0), (30, 2.0), (40, 3.0), (50, 4.0)):
        make_step(Storage.open(url), step, metrics={"mean_return": float(step), "eval_return": score}, config=own)
    told = r"--best-metric eval_retrun: no step .* \(did you mean eval_return\?\); use one of eval_return, mean_return"
    with pytest.raises(UserError, match=told):
        ckpt_commands.prune(url, keep_last=1, best_metric="eval_retrun")
    steps = lambda: [info.step for info in scan(Storage.open(url))]  # noqa: E731
    assert steps() == [50, 40, 30, 20, 10]  # refused: nothing deleted
    assert ckpt_commands.prune(url, keep_last=1) == 0  # the run's best (by eval_return) and its pinned step stay
    assert "retention: keep_last=1, keep_best=1 (eval_return), keep_every=0, pinned=[10]" in capsys.readouterr().out
    assert steps() == [50, 20, 10]
    assert ckpt_commands.prune(url, keep_last=1, keep_best=0) == 0
    assert steps() == [50, 10]


def test_prune_keeps_an_incomplete_step_written_lately_and_deletes_it_once_abandoned(run, capsys):
    """An incomplete step older than the newest verified one is an abandoned save, unless it was written lately:
    then it may be a save in flight of a run on another host, and ``prune`` leaves it until it is old."""
    storage = Storage.open(run)
    write_file(storage, 15, "common.pt", b"half a save")
    assert ckpt_commands.prune(run, keep_last=5) == 0
    assert "keeping step 15 (incomplete, last written 0 s ago: maybe a save in flight)" in capsys.readouterr().out
    assert 15 in [info.step for info in scan(storage)]
    old = time.time() - ABANDONED_AFTER - 1
    os.utime(f"{run}/checkpoints/step-000000015/common.pt", (old, old))
    assert ckpt_commands.prune(run, keep_last=5) == 0
    assert "deleting step 15 (abandoned, never committed)" in capsys.readouterr().out
    assert 15 not in [info.step for info in scan(storage)]


def test_a_part_of_a_storage_that_holds_no_step_is_told_what_to_pass_instead(run, monkeypatch):
    """A run's checkpoints/ directory, a step set aside under quarantine/, a policy snapshot or a file (an exported
    policy, a manifest) as the URL of a command that reads."""
    set_aside = f"{run}/quarantine/step-000000030.1"
    os.makedirs(set_aside)
    snapshot = f"{run}/policies/step-000000030"
    os.makedirs(snapshot)
    Path(f"{run}/policy.onnx").write_bytes(b"an exported policy")
    snapshot_fix = f"that is a policy snapshot of {run} (ftrain play and export take it): pass {run} for checkpoints"
    file_fix = "is a file: pass a run's storage (the directory holding checkpoints/) or one step directory"
    cases = [
        (ckpt_commands.ls, f"{run}/checkpoints", f"that is the checkpoints/ directory of {run}: pass {run}"),
        (resolve_checkpoint_url, f"{run}/checkpoints/", f"that is the checkpoints/ directory of {run}: pass {run}"),
        (ckpt_commands.show, set_aside, f"set aside under quarantine/, out of the history of {run}: see ftrain"),
        (ckpt_commands.show, snapshot, snapshot_fix),
        (ckpt_commands.verify, f"{snapshot}/", snapshot_fix),
        (ckpt_commands.show, f"{run}/policy.onnx", file_fix),
        (ckpt_commands.show, f"{run}/checkpoints/step-000000030/MANIFEST.json", file_fix),
    ]
    for command, url, fix in cases:
        with pytest.raises(UserError) as refused:
            command(url)
        assert fix in str(refused.value), (url, str(refused.value))
    monkeypatch.chdir(run)
    with pytest.raises(UserError, match=r"that is the checkpoints/ directory of \.: pass \.$"):
        ckpt_commands.ls("checkpoints")  # from inside the run's storage
    with pytest.raises(UserError, match=r": pass a run's storage \(the directory holding checkpoints/\) or one step"):
        ckpt_commands.ls("memory://quarantine/step-000000005")  # a bucket: nothing above it to pass
    own = Storage.open(f"{run}/more/checkpoints")  # a storage of one's own named checkpoints: no hint of a parent
    own.write_exclusive("notes.txt", b"not a step")
    with pytest.raises(UserError) as refused:
        ckpt_commands.ls(own.url)
    assert str(refused.value).endswith(
        ": pass a run's storage (the directory holding checkpoints/) or one step directory"
    )


def test_a_path_without_checkpoints_is_told_what_the_command_takes(tmp_path):
    """Every ckpt command on a path that does not exist and on a directory without checkpoints: one line that says
    which, and what to pass: a step directory only to the commands that take one (``prune nonexist`` suggested a
    step directory, which prune then refused). Nothing is created."""
    empty = tmp_path / "empty"
    empty.mkdir()
    commands = {
        ckpt_commands.ls: True,
        ckpt_commands.verify: True,
        ckpt_commands.show: True,
        ckpt_commands.unquarantine: True,
        lambda url: ckpt_commands.prune(url, keep_last=1): False,
        lambda url: ckpt_commands.keep_line(url, 10): False,
    }
    for command, takes_a_step in commands.items():
        for path, said in [(tmp_path / "nothing", "does not exist"), (empty, "no checkpoints under")]:
            with pytest.raises(UserError) as refused:
                command(str(path))
            line = str(refused.value)
            assert said in line and str(path) in line, line
            assert line.endswith("(the directory holding checkpoints/)" + " or one step directory" * takes_a_step), line
    assert sorted(tmp_path.iterdir()) == [empty] and not list(empty.iterdir())


def test_bad_input_is_a_user_error(run, tmp_path):
    with pytest.raises(UserError, match="step-000000099 does not exist"):
        ckpt_commands.verify(f"{run}/checkpoints/step-000000099")
    with pytest.raises(UserError, match="not one step"):
        ckpt_commands.prune(f"{run}/checkpoints/step-000000010", keep_last=1)
    for rule, said in ({"keep_last": 0}, "--keep-last=0 must be at least 1"), ({"pinned": [-1]}, "--pin -1 is no step"):
        with pytest.raises(UserError, match=said):  # as checkpoint.keep_last and checkpoint.pinned in a config
            ckpt_commands.prune(run, **rule)
    for dry_run in (True, False):  # a typo, not a step: refused before anything is deleted
        with pytest.raises(UserError, match=rf"^--pin 999: {re.escape(run)} holds no step 999; see ftrain ckpt ls"):
            ckpt_commands.prune(run, keep_last=1, pinned=[10, 999], dry_run=dry_run)
    assert 20 in [info.step for info in scan(Storage.open(run))]
    with pytest.raises(UserError, match="no usable manifest"):
        ckpt_commands.show(f"{run}/checkpoints/step-000000040")


def test_commands_on_s3(s3_url, capsys):
    url, options = s3_url
    build_tree(Storage.open(url, options))
    assert ckpt_commands.ls(url, options) == 0
    assert lines_by_step(capsys.readouterr().out)[25].split()[1] == "corrupt"
    assert ckpt_commands.verify(f"{url}/checkpoints/step-000000030", options) == 0
    assert ckpt_commands.verify(url, options) == 1
    assert ckpt_commands.prune(url, keep_last=2, options=options) == 0
    assert [info.step for info in scan(Storage.open(url, options))] == [40, 30, 25, 20]


@pytest.mark.slow  # an ftrain process of its own
def test_output_into_a_pipe_whose_reader_has_gone_ends_quietly(run):
    """``ftrain ckpt show URL | head -1``: once ``head`` has its line and exits, the next write fails (EPIPE); that
    ends the command like any tool killed by SIGPIPE (141), with no traceback."""
    show = [sys.executable, "-m", "ftrain", "ckpt", "show", run, "--json"]
    piped = subprocess.run(
        f"{shlex.join(show)} | head -1", shell=True, cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert piped.stdout == "{\n"
    assert "Traceback" not in piped.stderr and "BrokenPipeError" not in piped.stderr, piped.stderr

    read, write = os.pipe()
    os.close(read)  # the reader has gone before the first write: the write always fails
    with os.fdopen(write, "wb") as output:
        gone = subprocess.run(show, cwd=REPO, stdout=output, stderr=subprocess.PIPE, text=True, timeout=60)
    assert gone.returncode == 128 + signal.SIGPIPE
    assert "Traceback" not in gone.stderr and "BrokenPipeError" not in gone.stderr, gone.stderr


def test_verify_on_a_terminal_counts_the_steps_it_checks_and_clears_the_line_before_each_result(run, tmp_path) -> None:
    shown = on_a_terminal([sys.executable, "-m", "ftrain", "ckpt", "verify", run], tmp_path, code=1)
    counted = re.findall(r"\rckpt verify: (\d)/4 steps \(\d+%\)(?:, ETA \d+s)? \(step (\d+): [\d.]+ KiB\)", shown)
    assert counted == [("0", "30"), ("1", "25"), ("2", "20"), ("3", "10")], repr(shown)  # committed steps, newest first
    stays = [line.rsplit("\r", 1)[-1].strip() for line in shown.replace("\r\n", "\n").splitlines()]
    results = [line.split(":")[0] for line in stays if line.startswith("step ")]
    assert results == [f"step {step}" for step in (40, 30, 25, 20, 10)]  # each on a line of its own, the count wiped
    assert stays[-1] == "3 of 4 committed steps verified; 1 incomplete (never committed)"


def test_a_step_named_from_inside_its_storage_is_that_step(run, monkeypatch, capsys):
    """Generated cases: each step of a storage (committed or set aside), named by its path relative to each directory
    in and above the storage, is the step its full path names: ``ckpt show`` shows it, ``unquarantine`` finds the one
    set aside, and a storage inside it is refused (named from inside ``checkpoints/``, a step was 'no checkpoints')."""
    import shutil
    from pathlib import Path

    from ftrain.ckpt.format import parse_checkpoint_url
    from ftrain.ckpt.steps import check_storage_place, set_aside_location

    root = Path(run)
    shutil.copytree(root / "checkpoints" / "step-000000030", root / "quarantine" / "step-000000030")
    places = [root.parent, root, root / "checkpoints", root / "quarantine", root / "checkpoints" / "step-000000010"]
    checked = 0
    for cwd in places:
        monkeypatch.chdir(cwd)
        for parent, step in [("checkpoints", 10), ("checkpoints", 20), ("checkpoints", 30), ("quarantine", 30)]:
            named = os.path.relpath(root / parent / f"step-{step:09d}", cwd)
            if parent == "checkpoints":
                found, number = parse_checkpoint_url(named)
                assert (Path(found).resolve(), number) == (root, step), (cwd, named)
                assert ckpt_commands.show(named) == 0 and f"step: {step}\n" in capsys.readouterr().out, (cwd, named)
            else:
                found, directory = set_aside_location(named)
                assert (Path(found).resolve(), directory) == (root, "step-000000030"), (cwd, named)
            with pytest.raises(UserError, match=" is inside "):
                check_storage_place(os.path.join(named, "sub"))
            checked += 1
    monkeypatch.chdir(root / "checkpoints")
    with pytest.raises(UserError, match=f"that is the checkpoints/ directory of {root}: pass {root}$"):
        ckpt_commands.ls(".")
    monkeypatch.chdir(root / "quarantine")
    with pytest.raises(UserError, match=f"set aside under quarantine/, out of the history of {root}: see "):
        ckpt_commands.show("step-000000030")  # what to pass instead, as for its full path
    print(f"{checked} steps named from inside their storage found")
    assert checked == 20


def test_a_step_set_aside_goes_back_only_where_it_continues_the_line_and_nothing_else_changes(tmp_path, capsys):
    """Generated cases: 40 seeded schedules of runs on one storage, each resumed (``select_resume`` and
    ``clear_newer``, what a run's start does) after 0-2 of its newest steps were damaged, committing 0-3 steps on.
    Every step set aside is then repaired and put back with ``ftrain ckpt unquarantine``. Where it goes back
    (exit 0) its files are the ones set aside, the storage holds one line with it on it and resume takes the line's
    head; where it is refused (its number taken, or off the line), nothing in the storage changes."""
    import random

    from ftrain.ckpt.lineage import history
    from ftrain.ckpt.steps import ASIDE, clear_newer, select_resume

    outcomes = {"back": 0, "taken": 0, "off the line": 0}
    for case in range(40):
        draw, storage = random.Random(case), Storage.open(str(tmp_path / f"run-{case}"))
        originals, parent, step = {}, None, 0
        for generation in range(1, draw.randint(2, 4) + 1):
            if generation > 1:  # a restart after damage to the newest steps
                for info in scan(storage)[: draw.randint(0, 2)]:
                    flip_shard_byte(storage, info.step)
                selected = select_resume(storage, log=lambda line: None)
                step, parent = (selected[0], selected[1]) if selected else (0, None)
                clear_newer(storage, step, log=lambda line: None)
            for _ in range(draw.randint(0 if generation > 1 else 1, 3)):
                step += 2
                parent = commit_step(storage, step, generation, parent)
                originals[parent["state_sha256"]] = shard_of(generation, step)
        for directory in storage.list_dirs(ASIDE):
            source = f"{ASIDE}/{directory}"
            manifest = json.loads(storage.read(f"{source}/MANIFEST.json"))
            storage.write_replace(f"{source}/rank-00001.pt", originals[manifest["state_sha256"]])  # repaired
            before = tree(storage)
            assert ckpt_commands.verify(storage.where(source)) == 0, (case, directory)  # the repair, checked in place
            assert f"to put it back: ftrain ckpt unquarantine {storage.where(source)}" in capsys.readouterr().out
            assert tree(storage) == before, (case, directory)
            try:
                code = ckpt_commands.unquarantine(storage.where(source))
            except UserError as refused:
                outcomes["taken" if "holds the run's own step" in str(refused) else "off the line"] += 1
                assert tree(storage) == before, (case, directory, str(refused))
                continue
            assert code == 0 and "continues the storage's line" in capsys.readouterr().out, (case, directory)
            back = manifest["step"]
            assert {name: data for name, data in tree(storage).items() if name.startswith(step_dir(back))} == {
                name.replace(source, step_dir(back)): data
                for name, data in before.items()
                if name.startswith(source + "/") and not name.endswith("QUARANTINED.json")
            }
            past = history(scan(storage, full=True))
            assert back in past.line and not past.forks and not past.superseded, (case, directory, past)
            assert select_resume(storage, log=lambda line: None)[0] == past.line[0]
            outcomes["back"] += 1
    print(f"40 schedules, steps set aside put back or refused: {outcomes}")
    assert all(outcomes.values()), outcomes


def test_a_step_set_aside_that_would_fork_the_storage_or_does_not_verify_stays_aside(tmp_path, capsys):
    """The cases the schedules above do not reach: a step a person set aside with ``prune --keep-line`` (putting it
    back would fork the storage again), one whose shard does not verify (exit 1, nothing copied), one without a
    manifest, a directory that is not there, and a step number holding files of a save cut short. Each leaves the
    storage as it was."""
    from ftrain.ckpt.steps import ASIDE

    storage = Storage.open(str(tmp_path / "run"))
    ten = commit_step(storage, 10, 1, None)
    commit_step(storage, 30, 1, commit_step(storage, 20, 1, ten))
    commit_step(storage, 25, 1, ten)  # a second line from step 10: a fork
    cases = ((20, "30 descends", "--keep-line 30"), (10, "30, 25, 20 descend", "--keep-line 30 or --keep-line 25"))
    for inner, later, ends in cases:  # a step newer steps descend from ends no line: the ends of theirs are named
        with pytest.raises(UserError) as refused:
            ckpt_commands.keep_line(storage.url, inner)
        assert str(refused.value) == (
            f"step {inner} does not end a line of descent: {later} from it; keep a line that ends there ({ends}), or "
            f"train on from step {inner} in another storage: --storage NEW resume={storage.where(step_dir(inner))}"
        )
        assert not storage.list_dirs(ASIDE)
    newer = Storage.open(str(tmp_path / "newer"))  # generation 2 went on from 20; generation 1's 30 landed late
    twenty = commit_step(newer, 20, 1, commit_step(newer, 10, 1, None))
    commit_step(newer, 25, 2, twenty)
    commit_step(newer, 30, 1, twenty)
    with pytest.raises(UserError, match=r"keep a line that ends there \(--keep-line 25 or --keep-line 30\)"):
        ckpt_commands.keep_line(newer.url, 20)  # the newer generation's end first, though its number is lower
    assert ckpt_commands.keep_line(storage.url, 25) == 0
    assert sorted(storage.list_dirs(ASIDE)) == ["step-000000020", "step-000000030"]
    flip_shard_byte(storage, 25)
    assert ckpt_commands.prune(storage.url, keep_last=5) == 0  # nothing deleted: the corrupt step stays
    os.makedirs(f"{storage.url}/{ASIDE}/step-000000040")  # set aside without a manifest
    os.makedirs(f"{storage.url}/checkpoints/step-000000020")
    with open(f"{storage.url}/checkpoints/step-000000020/common.pt", "wb") as half:
        half.write(b"a save cut short")
    refusals = [
        ("step-000000030", "does not continue the storage's line of descent (steps 25, 10)"),
        ("step-000000020", "holds files of a step never committed (a save or a copy cut short)"),
        ("step-000000040", "has no manifest (never committed): nothing to reinstate"),
        ("step-000000050", "does not exist: see ftrain ckpt ls"),
    ]
    with pytest.raises(UserError, match=r"step-000000050 does not exist: see ftrain ckpt ls"):
        ckpt_commands.verify(f"{storage.url}/{ASIDE}/step-000000050")
    for directory, why in refusals:
        before = tree(storage)
        with pytest.raises(UserError, match=re.escape(why)):
            ckpt_commands.unquarantine(f"{storage.url}/{ASIDE}/{directory}")
        assert tree(storage) == before, directory
    os.remove(f"{storage.url}/checkpoints/step-000000020/common.pt")
    os.rmdir(f"{storage.url}/checkpoints/step-000000020")
    os.rename(f"{storage.url}/checkpoints/step-000000025", f"{storage.url}/{ASIDE}/step-000000025")  # shard damaged
    before = tree(storage)
    for spelt in ("step-000000025", "step-25/"):  # the number short, as checkpoints/ takes it too
        assert ckpt_commands.verify(f"{storage.url}/{ASIDE}/{spelt}") == 1
        assert re.search(r"step-000000025: FAILED\n  rank-00001.pt: .*sha256", capsys.readouterr().out)
    assert ckpt_commands.unquarantine(f"{storage.url}/{ASIDE}/step-25") == 1
    assert "stays set aside: it does not verify" in capsys.readouterr().out
    assert tree(storage) == before and not os.path.exists(f"{storage.url}/checkpoints/step-000000025")


def test_a_held_storage_refuses_unquarantine_without_offering_a_force_it_has_not(tmp_path, capsys):
    from ftrain.ckpt.lease import Lease
    from ftrain.errors import EXIT_STORAGE_HELD

    storage = Storage.open(str(tmp_path / "run"))
    make_step(storage, 10)
    ckpt_commands.quarantine(storage, 10, "looked at by hand")
    other = Lease(storage, "a-run", print)
    other.hold()
    try:
        assert ckpt_commands.unquarantine(f"{storage.url}/checkpoints/step-000000010") == EXIT_STORAGE_HELD
        assert ckpt_commands.prune(storage.url, keep_last=1) == EXIT_STORAGE_HELD
    finally:
        other.release()
    unquarantine, prune = capsys.readouterr().err.strip().splitlines()[-2:]
    assert unquarantine.startswith("ftrain: error: ckpt unquarantine refused: ") and "--force" not in unquarantine
    assert prune.endswith("(or pass --force to prune anyway)")


def shard_of(generation: int, step: int) -> bytes:
    return encode({"rank": 1, "rng": [generation, step] * 40})


def commit_step(storage: Storage, step: int, generation: int, parent: dict | None) -> dict:
    """Commit a small step of ``generation`` continuing ``parent`` (a manifest, or None for a fresh start); its
    manifest."""
    import hashlib

    from ftrain.ckpt.format import commit

    data, shard = encode({"generation": generation, "step": step}), shard_of(generation, step)
    files = {"common.pt": write_file(storage, step, "common.pt", data)}
    files["rank-00001.pt"] = write_file(storage, step, "rank-00001.pt", shard)
    link = {"step": parent["step"], "state_sha256": parent["state_sha256"]} if parent else None
    meta = {"generation": generation, "parent": link, "state_sha256": hashlib.sha256(data + shard).hexdigest()}
    return commit(storage, step, files, meta)


def tree(storage: Storage) -> dict[str, bytes]:
    """Every file of a local storage and its bytes."""
    root = storage.url
    return {
        os.path.relpath(os.path.join(top, name), root): open(os.path.join(top, name), "rb").read()
        for top, _, names in os.walk(root)
        for name in names
        if not name.startswith("LEASE")
    }


def test_a_command_a_line_offers_pastes_as_it_is_for_a_path_with_a_space(tmp_path):
    import shlex

    run = str(tmp_path / "my run")
    make_step(Storage.open(run), 10)
    with pytest.raises(UserError) as refused:
        ckpt_commands.show(f"{run}/checkpoints/step-000000020")
    hint = str(refused.value).rpartition("see ")[2]
    assert shlex.split(hint) == ["ftrain", "ckpt", "ls", run], hint


def test_a_storage_whose_every_step_is_corrupt_names_commands_that_run_as_written(tmp_path, capsys):
    """A start on a storage where no step verifies refuses, and names the commands that inspect and remove the
    corrupt steps: each runs as written (the prune it named lacked the storage, and argparse refused it), and the
    next start begins afresh."""
    from ftrain.ckpt.resume import decide
    from ftrain.cli import main
    from ftrain.config import load_config

    storage = Storage.open(str(tmp_path / "my run"))
    for step in (10, 20):
        make_step(storage, step)
        flip_shard_byte(storage, step)
    config = load_config(None, [f"storage.url={storage.url}"])
    refused = decide(config, storage, print, 1)
    assert refused["kind"] == "usage", refused
    named = re.findall(r"\((ftrain ckpt [^)]*)\)", refused["why"])
    assert [shlex.split(line)[:3] for line in named] == [["ftrain", "ckpt", "ls"], ["ftrain", "ckpt", "prune"]]
    for line in named:
        assert main(shlex.split(line)[1:]) == 0, line
    pruned = capsys.readouterr().out
    assert "deleting step 20" in pruned and "deleting step 10" in pruned, pruned
    assert decide(config, storage, print, 1)["kind"] == "fresh"


def test_an_incomplete_step_of_a_storage_held_now_is_said_to_be_maybe_a_save_in_flight(run, capsys):
    """ls and verify, and play and export (``resolve_checkpoint_url``: the newest step, or the step named), beside a
    live run called its save in flight 'never committed': where the storage's lease is held now, they name the
    holder; without one, or with an expired one, not."""
    from ftrain.ckpt.lease import Entry, Record
    from ftrain.procfs import Process

    storage = Storage.open(run)
    said = "holds this storage now: an incomplete step may be its save in flight"
    for lease, held in [(None, False), (time.time() - 3600, False), (time.time(), True)]:
        if lease is not None:
            far = Process("node-far-away", 4242, 123, "another-boot-id", "pid:[1]")  # alive by its renewals only
            storage.write_replace("LEASE.json", Record("live-run", 3, 60.0, (Entry(far, lease),)).encode())
        for command in (ckpt_commands.ls, ckpt_commands.verify):
            command(run)
            out = capsys.readouterr().out
            assert (f"run live-run (pid 4242 on host node-far-away) {said}" in out) == held, (lease, out)
        skipped = []
        assert resolve_checkpoint_url(run, log=skipped.append)[1] == 30
        in_flight = f"skipping checkpoint step 40: incomplete (run live-run (pid 4242 on host node-far-away) {said})"
        assert (in_flight in skipped) == held and len(skipped) == 1, skipped
        with pytest.raises(UserError) as refused:
            resolve_checkpoint_url(f"{run}/checkpoints/step-000000040")
        named = f"checkpoint {run}/checkpoints/step-000000040 is not committed (run live-run (pid 4242 on host "
        assert (
            str(refused.value).startswith(named) and str(refused.value).endswith(f"or pass {run} for its newest")
        ) == held
        assert (
            "(MANIFEST.json: missing: not committed (a save cut short, or in flight)): pick another"
            in str(refused.value)
        ) != held


@pytest.mark.slow
def test_verify_beside_a_live_run_whose_retention_deletes_steps_never_fails(tmp_path, capsys) -> None:
    """``ckpt verify`` again and again beside a run that saves every iteration and keeps one step: a step its
    retention deletes between verify's listing and its check is said to be deleted meanwhile, never FAILED (a
    monitoring script's false alarm); the rounds that met a deletion are counted and printed."""
    run = tmp_path / "run"
    proc = start_train(
        run, "iterations=100000", "checkpoint.interval=1", "checkpoint.keep_last=1", "checkpoint.keep_best=0"
    )
    try:
        wait_for(lambda: len(manifests(run)) >= 1, "a first save")
        rounds = met = 0
        while met < 3 and rounds < 400:
            code = ckpt_commands.verify(str(run))
            out = capsys.readouterr().out
            assert code == 0 and "FAILED" not in out, out
            met += "deleted while it was checked" in out
            rounds += 1
    finally:
        kill_tree(proc)
    print(f"{rounds} verify rounds beside the run, {met} of them met a step deleted while it was checked")
    assert met >= 1


def test_a_run_with_no_save_yet_and_an_empty_step_directory_are_told_as_what_they_are(tmp_path, capsys) -> None:
    """A run's storage before its first save (its LEASE.json there, no step) is a run's storage with none yet, not
    'pass a run's storage'; an empty step directory (a save that wrote nothing yet), listed as incomplete, is
    incomplete when named too: verify exits 1 (``verify STEP && use STEP``), show and play refuse it as such."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "LEASE.json").write_text('{"run_id": "r", "generation": 1, "ttl": 60, "holders": []}')
    with pytest.raises(
        UserError, match=rf"^no checkpoints under {run} yet: the run that took it has saved none so far$"
    ):
        ckpt_commands.ls(str(run))
    (run / "checkpoints" / "step-000000040").mkdir(parents=True)
    step = f"{run}/checkpoints/step-000000040"
    assert ckpt_commands.verify(step) == 1
    out = capsys.readouterr().out
    assert out.startswith("step 40: incomplete (never committed: no manifest; ") and "1 incomplete" in out, out
    with pytest.raises(
        UserError,
        match=r"does not verify \(MANIFEST.json: missing: not committed \(a save cut short, or in flight\)",
    ):
        resolve_checkpoint_url(step)
    with pytest.raises(UserError, match=r"step-000000041 does not exist: see ftrain ckpt ls "):
        ckpt_commands.verify(f"{run}/checkpoints/step-000000041")
