"""One run per storage, with real processes: a second ``ftrain supervise``, ``torchrun -m ftrain train`` or
``ftrain train`` on the storage of a live run, or a second launch under its run id, is refused with one line naming
the holder (exit 8), and the first run ends as it would have alone; the same command again right after a SIGKILL
takes over at once; a lease that expired on another host is taken over."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ftrain import procfs
from ftrain.ckpt import cas
from ftrain.ckpt.lease import LEASE, TTL_ENV, Entry, Record
from ftrain.ckpt.storage import Storage
from ftrain.errors import EXIT_STORAGE_HELD
from ftrain.identity import RUN_ID_ENV
from ftrain.procfs import Process
from ftrain.supervise.attempt import TORCHRUN
from ftrain.supervise.auth import SECRET_ENV

import helpers
from helpers import (
    HOLD_LOCK,
    REPO,
    SMOKE,
    TESTS,
    Hold,
    child_env,
    create_bucket,
    events,
    final_manifest,
    finish,
    free_port,
    kill_tree,
    launch,
    manifests,
    run_train,
    train_command,
    training,
    wait_for,
)

pytestmark = pytest.mark.slow

OVERRIDES = ("iterations=8", "log.console=false")
HOLD_ENV = {"PYTHONPATH": str(TESTS)}
"""What a first run that holds (``Hold``) needs: the intruders start and are refused while it holds."""


def supervise_command(storage: str | Path, *overrides: str) -> list[str]:
    return helpers.supervise_command(storage, *OVERRIDES, *overrides)


def intrude(command: list[str], env: dict | None = None) -> subprocess.Popen:
    return subprocess.Popen(command, cwd=REPO, env=child_env(env), stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def refused(proc: subprocess.Popen, holders: list[int], by: str = "another run") -> tuple[str, str]:
    """The one line that refused ``proc``, which must say it is held ``by`` one of the first run's ``holders``
    (pids), and all its output."""
    stdout, stderr = proc.communicate(timeout=120)
    output = stdout.decode() + stderr.decode()
    lines = [line for line in output.splitlines() if f"is held by {by}" in line]
    assert lines, f"no refusal in:\n{output}"
    assert any(f"pid {pid} on host " in lines[0] for pid in holders), lines[0]
    return lines[0], output


@pytest.fixture
def reference(reference_state) -> str:
    """The state of the same 2-rank run, alone on its storage."""
    return reference_state(8)


def released(storage: Storage | Path) -> bool:
    """The lease has no holder left (its record stays, with its generation)."""
    storage = storage if isinstance(storage, Storage) else Storage.open(str(storage))
    return Record.decode(storage.read(LEASE)).entries == ()


def test_a_second_run_beside_a_supervised_one_is_refused_and_the_first_ends_as_alone(tmp_path, reference):
    """Refused too: a second launch under the first's run id (one FTRAIN_RUN_ID: a batch script run twice), which is
    another start of the run, not a node of it."""
    storage, hold = tmp_path / "run", Hold(tmp_path, 4)
    env = child_env({**HOLD_ENV, RUN_ID_ENV: "job-1"})
    first = launch(supervise_command(storage, hold.override), cwd=REPO, env=env)
    hold.held()
    supervise = intrude(supervise_command(storage))
    plain = intrude(train_command(storage, *OVERRIDES))
    again = {RUN_ID_ENV: "job-1"}
    supervise_again = intrude(supervise_command(storage, f"log_dir={tmp_path / 'again'}"), env=again)
    plain_again = intrude(train_command(storage, *OVERRIDES, f"log_dir={tmp_path / 'plain' / 'logs'}"), env=again)
    for proc in (supervise, plain, supervise_again, plain_again):
        assert proc.wait(timeout=120) == EXIT_STORAGE_HELD
    assert first.poll() is None
    line, output = refused(supervise, [first.pid])
    assert line.startswith("ftrain supervise: error: storage ") and output == line + "\n"  # nothing else
    assert "lease ends at " in line
    line, output = refused(plain, [first.pid])
    assert line.startswith("ftrain: error: storage ") and output == line + "\n"
    for proc, program in ((supervise_again, "ftrain supervise"), (plain_again, "ftrain")):
        line, output = refused(proc, [first.pid], by="another start of run job-1")
        assert line.startswith(f"{program}: error: storage ") and output == line + "\n", output
    assert not (tmp_path / "again" / "events.jsonl").exists()
    assert not (tmp_path / "plain").exists()  # the log directory it made for itself, removed when it was refused

    hold.release()
    assert finish(first) == 0
    assert final_manifest(storage)["state_sha256"] == reference
    names = [event["event"] for event in events(storage)]
    assert names.count("start") == 1 and names[-2:] == ["done", "summary"]  # the refused runs wrote nothing here
    assert released(storage)  # at the end: the same command again starts at once


def test_a_second_torchrun_beside_a_torchrun_run_is_refused_and_the_first_ends_as_alone(
    tmp_path, reference, s3_url, s3_env
):
    url, _ = s3_url
    hold = Hold(tmp_path, 4)
    log_dir = f"log_dir={tmp_path / 'logs'}"
    first = launch(
        train_command(url, *OVERRIDES, log_dir, hold.override, ranks=2), cwd=REPO, env=child_env({**s3_env, **HOLD_ENV})
    )
    hold.held()
    holders = procfs.descendants(first.pid)
    second = intrude(train_command(url, *OVERRIDES, log_dir, ranks=2), env=s3_env)
    supervise = intrude(supervise_command(url, log_dir), env=s3_env)
    assert supervise.wait(timeout=120) == EXIT_STORAGE_HELD
    assert second.wait(timeout=120) != 0  # torchrun exits 1 when a worker fails, whatever its code
    assert first.poll() is None
    refused(supervise, holders)
    line, output = refused(second, holders)
    assert line.startswith("ftrain: error: storage ")
    assert re.search(rf"exitcode\s*:\s*{EXIT_STORAGE_HELD}\b", output)  # torchrun's report: the ranks exited 8

    hold.release()
    assert finish(first) == 0
    storage = Storage.open(*s3_url)
    step = max(storage.list_dirs("checkpoints"))
    assert json.loads(storage.read(f"checkpoints/{step}/MANIFEST.json"))["state_sha256"] == reference
    assert released(storage)


def test_the_same_command_again_after_a_sigkill_takes_over_at_once(tmp_path):
    storage = tmp_path / "run"
    command = supervise_command(storage, "iterations=40", "checkpoint.interval=10")
    first = launch(command, cwd=REPO, env=child_env())
    training(storage / "heartbeat", 2)
    kill_tree(first)  # the supervisor, torchrun and the workers at once, like a lost machine
    held = Record.decode((storage / LEASE).read_bytes())
    assert [entry.process.pid for entry in held.entries] == [first.pid]

    started = time.time()
    again = launch(command, cwd=REPO, env=child_env(), stderr=subprocess.PIPE)
    taken = wait_for(lambda: [e for e in events(storage) if e["event"] == "lease"], "the lease taken over")[0]
    assert taken["time"] - started < 45  # less than the lease's 60 s: the dead supervisor was seen at once
    assert f"pid {first.pid} on host " in taken["detail"] and "is gone" in taken["detail"]
    assert finish(again) == 0
    assert "took over the lease of" in again.stderr.read().decode()
    assert final_manifest(storage)["step"] == 40


def test_every_node_of_a_supervised_run_is_admitted_and_holds_the_lease(tmp_path):
    storage = tmp_path / "run"
    nodes = ["--nnodes=2", "--nproc-per-node=1", f"--rdzv-endpoint=127.0.0.1:{free_port()}"]
    env = child_env({SECRET_ENV: "ftrain-test-one-run-secret"})
    supervisors = [
        launch([*supervise_command(storage, "iterations=60"), *nodes, f"--node-rank={node}"], cwd=REPO, env=env)
        for node in (0, 1)
    ]

    def holders() -> set[int]:
        lease = storage / LEASE
        return {e.process.pid for e in Record.decode(lease.read_bytes()).entries} if lease.exists() else set()

    wait_for(lambda: holders() == {proc.pid for proc in supervisors}, "both supervisors in the lease")
    assert [finish(proc) for proc in supervisors] == [0, 0]
    assert final_manifest(storage)["step"] == 60
    assert released(storage)


def test_a_lease_that_expired_on_another_host_is_taken_over(tmp_path, s3_url, s3_env):
    url, options = s3_url
    foreign = Process("node-far-away", 4242, 123, "another-boot-id", "pid:[1]")
    expired = Record("far-run", 7, 2.0, (Entry(foreign, time.time() - 120),))
    Storage.open(url, options).write_replace(LEASE, expired.encode())
    time.sleep(3.5)  # not renewed for longer than its ttl by the storage's clock too (whole seconds on S3)

    result = run_train(url, f"log_dir={tmp_path / 'logs'}", env=s3_env)
    assert "took over the lease of" in result.stdout and "from run far-run" in result.stdout
    assert "the lease of pid 4242 on host node-far-away expired at" in result.stdout
    assert released(Storage.open(url, options))  # at the end, at the generation after the expired one's
    assert Record.decode(Storage.open(url, options).read(LEASE)).generation == 8


def test_two_runs_of_one_config_from_one_directory_keep_their_logs_apart(tmp_path, s3_server, s3_env) -> None:
    """exp1 and exp2 from one checkout: two storages, so two log directories (``runs/<name>/s3/<bucket>/<prefix>``),
    each with one run's events, metrics and heartbeats; neither stops, prunes or restarts anything of the other. A
    supervisor told to log into a directory in use is refused with one line and touches nothing."""
    bucket, hold = create_bucket(s3_server), Hold(tmp_path, 3)  # both runs hold until the third is refused

    def command(prefix: str, *overrides: str) -> list[str]:
        return helpers.supervise_command(f"s3://{bucket}/{prefix}", "iterations=40", *overrides, ranks=1)

    env = child_env({**s3_env, **HOLD_ENV})
    runs = {prefix: launch(command(prefix, hold.override), cwd=tmp_path, env=env) for prefix in ("exp1", "exp2")}
    logs = {prefix: tmp_path / "runs" / "smoke" / "s3" / bucket / prefix for prefix in runs}
    for prefix in runs:
        training(logs[prefix] / "heartbeat", 2, ranks=[0])
    shared = Path("runs/smoke/s3", bucket, "exp1")  # a third storage, told to log where exp1 logs
    third = command("exp3", f"log_dir={shared}")
    again = subprocess.run(third, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert again.returncode == 2, again.stderr
    assert f"log directory {shared} is in use by another run (supervisor pid " in again.stderr, again.stderr
    assert len(again.stderr.strip().splitlines()) == 1, again.stderr
    hold.release()
    assert [finish(proc, timeout=180) for proc in runs.values()] == [0, 0]
    for prefix, log_dir in logs.items():
        recorded = events(log_dir)
        assert [e["event"] for e in recorded].count("start") == 1 and recorded[-1]["event"] == "summary", recorded
        assert recorded[-1]["restarts"] == 0, recorded[-1]
        with (log_dir / "metrics.csv").open() as file:
            assert [int(row["iteration"]) for row in csv.DictReader(file)] == list(range(1, 41)), prefix
        spooled = sorted(path.parent.name for path in (log_dir / "spool").glob("checkpoints/*/MANIFEST.json"))
        assert spooled and spooled[-1] == "step-000000040", (prefix, spooled)


def test_a_lease_taken_while_the_workers_train_stops_them_at_once_with_exit_8(tmp_path) -> None:
    """Another run takes the storage while this one trains (its lease expired while it was cut off, say): the
    supervisor's next renewal finds the newer generation and stops its workers there, before they commit anything
    more (they are held after iteration 3: without the supervisor they would wait), and exits 8 with one line."""
    storage, hold = tmp_path / "run", Hold(tmp_path, 3)
    console = tmp_path / "console"
    proc = launch_short_lease(helpers.supervise_command(storage, "iterations=40", hold.override, ranks=1), console)
    hold.held()
    committed = sorted(manifests(storage))
    take_lease_elsewhere(storage)
    assert finish(proc, timeout=60) == EXIT_STORAGE_HELD
    said = console.read_text()
    assert "taken by run intruder (generation 2; this run's is 1)" in said and "its workers are stopped" in said, said
    assert "Traceback" not in said, said
    assert sorted(manifests(storage)) == committed  # nothing after the takeover
    assert [event["event"] for event in events(storage)][-2:] == ["storage_held", "summary"]


@pytest.mark.skipif(os.geteuid() != 0 or not shutil.which("unshare"), reason="another host: a UTS namespace (root)")
def test_a_run_paused_past_its_lease_whose_storage_another_run_took_commits_nothing_more(tmp_path) -> None:
    """Run A (a 4 s lease) is SIGSTOPped outside its lease's lock (paused inside it, A stalls every other run on
    this file system, B too: not what this test is about); run B, on "another host" (a hostname of its own: A's
    entry can only expire there), takes the lease at the next generation, trains on from A's newest step and ends.
    A, continued, commits nothing over B's steps: its rank 0 finds B's generation in the lease before its next
    manifest, and A stops with exit 8 and one line; its supervisor never takes the lease back."""
    storage = tmp_path / "run"
    command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node=1", SMOKE, "--storage", str(storage)]
    a_log = tmp_path / "a.log"
    with a_log.open("wb") as output:
        first = launch(
            [*command, "iterations=400", "checkpoint.interval=2"],
            cwd=REPO,
            env=child_env({TTL_ENV: "4"}),
            stdout=output,
            stderr=subprocess.STDOUT,
        )
    wait_for(lambda: len(manifests(storage)) >= 2, "run A's first commits", timeout=120)
    with cas.locked(Storage.open(str(storage)), LEASE):  # A paused outside its lease's lock, which would stall B
        paused = [first.pid, *procfs.descendants(first.pid)]
        for pid in paused:
            os.kill(pid, signal.SIGSTOP)
    try:
        time.sleep(5)  # past A's lease, which only expiry ends from another host
        newest = final_manifest(storage)["step"]
        assert {manifest["generation"] for manifest in manifests(storage).values()} == {1}
        elsewhere = ["unshare", "--uts", "sh", "-c", 'hostname elsewhere && exec "$@"', "sh"]
        b_log, b_arguments = tmp_path / "b.log", [f"iterations={newest + 10}", "checkpoint.interval=2"]
        with b_log.open("wb") as output:
            second = launch(
                [*elsewhere, *command, *b_arguments, f"log_dir={tmp_path / 'b'}"],
                cwd=REPO,
                env=child_env(),
                stdout=output,
                stderr=subprocess.STDOUT,
            )
        code = finish(second, timeout=120, output=b_log)
        said_b = b_log.read_text()
        assert code == 0, said_b[-3000:]
        assert "took over the lease of" in said_b and "expired at" in said_b
    finally:
        for pid in paused:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
    assert finish(first, timeout=120) == EXIT_STORAGE_HELD
    said = a_log.read_text()
    assert "Traceback" not in said, said
    assert "taken by run" in said and "(generation 2; this run's is 1): this run lost the storage" in said, said

    ending = final_manifest(storage)
    assert ending["step"] == newest + 10 and ending["generation"] == 2
    after = {step: manifest["generation"] for step, manifest in manifests(storage).items() if step > newest}
    assert after and set(after.values()) == {2}, after  # every step past the takeover is B's
    lease = Record.decode((storage / LEASE).read_bytes())
    assert (lease.generation, lease.entries) == (2, ())  # B's, released; A did not take it back


def launch_short_lease(command: list[str], console: Path) -> subprocess.Popen:
    """``command`` with a 3 s lease (renewed every second) and a run that may hold, its output into ``console``."""
    with console.open("wb") as output:
        env = child_env({TTL_ENV: "3", **HOLD_ENV})
        return launch(command, cwd=REPO, env=env, stdout=output, stderr=subprocess.STDOUT)


def take_lease_elsewhere(storage: Path) -> None:
    """Run "intruder" on another host takes the storage's lease at the next generation (its holder's lease expired
    while it was cut off, say)."""
    far = Process("node-far-away", 4242, 123, "another-boot-id", "pid:[1]")
    opened = Storage.open(str(storage))
    while True:  # as a host writes it: against the version it read (a plain write could be lost to a renewal)
        data, version = cas.read(opened, LEASE)
        intruder = Record("intruder", Record.decode(data).generation + 1, 60.0, (Entry(far, time.time()),))
        with contextlib.suppress(cas.Conflict):
            cas.write(opened, LEASE, intruder.encode(), version)
            return


def plain_torchrun(storage: Path, port: int, *overrides: str, launcher: str = "torch.distributed.run") -> list[str]:
    """torchrun as most users first type it: no --standalone, no --rdzv-id (torchrun's run id is then ``none`` for
    every run), a master port of its own; ``launcher``: ftrain's torchrun (``ftrun``) instead."""
    command = [sys.executable, "-m", launcher, "--nproc-per-node=2", f"--master-port={port}"]
    return [*command, "-m", "ftrain", "train", SMOKE, "--storage", str(storage), *OVERRIDES, *overrides]


def files(storage: Path) -> dict[str, object]:
    """Every file of a local storage, by path; the lease as who holds it, at which generation, since when: the holder
    renews it every 20 s (``renewed_at``), and a test on a slow machine outlasts that while it watches."""
    found: dict[str, object] = {
        str(path.relative_to(storage)): path.read_bytes() for path in sorted(storage.rglob("*")) if path.is_file()
    }
    if LEASE in found:
        lease = Record.decode(found[LEASE])
        holders = tuple((entry.process, entry.since) for entry in lease.entries)
        found[LEASE] = (lease.run_id, lease.generation, lease.ttl, holders)
    return found


def test_a_second_plain_torchrun_on_a_live_runs_storage_is_refused_in_one_line_and_writes_nothing(tmp_path, reference):
    """Two plain torchrun runs (torchrun's shared run id ``none``) are two runs: the second is refused within seconds,
    in ftrain's one line naming the holder (host, pid, since when), its ranks exit 8, the storage is byte for byte as
    before, and the first run ends as it would have alone."""
    storage, hold = tmp_path / "run", Hold(tmp_path, 4)
    first = launch(plain_torchrun(storage, free_port(), hold.override), cwd=REPO, env=child_env(HOLD_ENV))
    hold.held()
    holders, before = procfs.descendants(first.pid), files(storage)
    started = time.monotonic()
    second = intrude(plain_torchrun(storage, free_port()))
    assert second.wait(timeout=240) != 0
    assert (
        time.monotonic() - started < 120
    )  # a cold torchrun and two ranks (seconds here), not the collectives' timeout
    line, output = refused(second, holders)
    assert line.startswith("ftrain: error: storage ") and re.search(r" since \d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC", line)
    assert re.search(rf"exitcode\s*:\s*{EXIT_STORAGE_HELD}\b", output)  # torchrun's report: the ranks exited 8
    assert files(storage) == before, "the refused run must write nothing to the storage"
    ftrun = intrude(plain_torchrun(storage, free_port(), launcher=TORCHRUN))  # what README shows: ftrain's one line
    assert ftrun.wait(timeout=120) == EXIT_STORAGE_HELD
    line, output = refused(ftrun, holders)
    assert output == line + "\n" and line.startswith("ftrain: error: storage ")
    assert files(storage) == before
    assert first.poll() is None
    hold.release()
    assert finish(first) == 0
    assert final_manifest(storage)["state_sha256"] == reference
    assert {manifest["run_id"] for manifest in manifests(storage).values()} != {"none"}


def test_ckpt_prune_on_a_live_runs_storage_is_refused_and_deletes_nothing_unless_forced(tmp_path):
    storage, hold = tmp_path / "run", Hold(tmp_path, 6)
    first = launch(
        train_command(storage, "iterations=8", "checkpoint.keep_last=5", hold.override), env=child_env(HOLD_ENV)
    )
    hold.held()
    before = files(storage)
    prune = [sys.executable, "-m", "ftrain", "ckpt", "prune", str(storage), "--keep-last", "1"]
    refusal = subprocess.run(prune, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    assert refusal.returncode == EXIT_STORAGE_HELD
    assert refusal.stdout == "" and len(refusal.stderr.splitlines()) == 1, refusal.stderr
    assert (
        refusal.stderr.startswith("ftrain: error: ckpt prune refused: storage ")
        and f"pid {first.pid} " in refusal.stderr
    )
    assert "pass --force to prune anyway" in refusal.stderr
    assert files(storage) == before
    forced = subprocess.run([*prune, "--force"], cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    assert forced.returncode == 0 and sorted(manifests(storage)) == [4], (
        forced.stdout + forced.stderr
    )  # 6 is not saved yet
    hold.release()
    assert finish(first) == 0
    # the run gone, prune holds the lease itself (no best step kept: which is best differs with the CPU's kernels)
    after = subprocess.run([*prune, "--keep-best", "0"], cwd=REPO, env=child_env(), capture_output=True, text=True)
    assert after.returncode == 0 and "kept 1 committed step: 8" in after.stdout, after.stdout + after.stderr


def test_an_unsupervised_run_whose_lease_another_run_took_stops_at_once_with_exit_8(tmp_path) -> None:
    """No supervisor: rank 0's renewal finds the newer generation and the ranks stop at the next iteration boundary,
    exit 8 in one line, committing nothing more. No save is due for 1,000 iterations (one would be refused as well):
    the vote stops them, within seconds."""
    storage, hold = tmp_path / "run", Hold(tmp_path, 3)
    console = tmp_path / "console"
    command = train_command(storage, "iterations=100000", "checkpoint.interval=1000", hold.override, ranks=2)
    proc = launch_short_lease(command, console)
    hold.held()
    committed = sorted(manifests(storage))
    take_lease_elsewhere(storage)
    hold.release()
    released = time.monotonic()
    assert finish(proc, timeout=60) != 0
    assert time.monotonic() - released < 20, "the renewal (every second) and the next iteration's vote stop it"
    said = console.read_text()
    lines = re.findall(r"^ftrain: error: the lease of .*$", said, re.MULTILINE)  # ftrain's own (torchrun repeats it)
    assert len(lines) == 1 and lines[0].endswith("this run lost the storage and commits nothing more"), said
    assert re.search(rf"exitcode\s*:\s*{EXIT_STORAGE_HELD}\b", said), said
    assert sorted(manifests(storage)) == committed  # nothing after the takeover


def test_a_run_that_waits_for_a_lock_a_stopped_process_holds_says_who_holds_it_and_stops_on_sigterm(tmp_path):
    storage, output = tmp_path / "run", tmp_path / "supervise.log"
    holder = launch([sys.executable, "-c", HOLD_LOCK, str(storage)], env=child_env(), stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline() == b"held\n"
        with output.open("wb") as log:
            run = launch(supervise_command(storage, "iterations=4"), cwd=REPO, env=child_env(), stdout=log, stderr=log)
        said = lambda: output.read_text()  # noqa: E731
        waiting = wait_for(lambda: "has been locked for" in said() and said(), "the wait told", timeout=60)
        line = next(line for line in waiting.splitlines() if "has been locked for" in line)
        named = rf"{re.escape(str(storage))}/LEASE\.json\.lock has been locked for \d+ s by process {holder.pid} \("
        assert re.search(named, line), line
        assert "stopped): every commit and lease change on this storage waits for it" in line, line
        assert run.poll() is None and not manifests(storage)  # it waits, and nothing was written meanwhile
        run.send_signal(signal.SIGTERM)  # as SLURM or Ctrl-C would: it stops now, not once the lock is free
        assert finish(run, timeout=60, output=output) == 128 + signal.SIGTERM  # the lock stays held: any bound
        assert re.search(
            r"preempted: stopped by a signal while no workers ran \((newest step \d+|no step committed yet)\); run the "
            r"same command again to continue",
            said(),
        )
        assert [(event["event"], event.get("signal")) for event in events(storage)][:2] == [
            ("preempt", "SIGTERM"),
            ("preempted", None),
        ]
    finally:
        os.kill(holder.pid, signal.SIGCONT)
    assert finish(holder) == 0
    assert finish(launch(supervise_command(storage, "iterations=4"), cwd=REPO, env=child_env())) == 0  # the rerun
    assert final_manifest(storage)["step"] == 4
    assert "Traceback" not in said()
