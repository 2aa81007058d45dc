"""Outages of the storage, without mocks: a supervised 2-rank run on S3 (moto's server behind a proxy the test
switches). With torchrun killed deep inside a refusing outage, the restarted workers go on from the node-local spool
(``ftrain/ckpt/spool.py``), which the saves on the schedule kept up to date while the storage's tries came further and
further apart; with the spool off, a hanging server with a worker killed inside it is waited out by the supervisor.
Both end with exit 0 and the same ``state_sha256`` as an uninterrupted run. Outages are 15 s here (the issue's 45 s
and 90 s belong to launch/bench_chaos.py); lowered timeouts keep the waits short. Iterations last at least ``PACE``
(``probe_hooks.PacingHook``, which changes nothing that is trained), so that the faults land well before the last
iteration however fast the machine: about 60 of the 100 iterations pass before the outage ends."""

from __future__ import annotations

import contextlib
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
import types
from collections.abc import Iterator
from pathlib import Path

import botocore.exceptions
import pytest

from ftrain.ckpt.steps import select_resume
from ftrain.ckpt.storage import Storage
from ftrain.errors import EXIT_USAGE, UserError
from ftrain.heartbeat import read_heartbeats
from ftrain.supervise.outage import probe, short_of_space

from failing_mount import failing_mount
from helpers import (
    REPO,
    SMOKE,
    TESTS,
    Hold,
    StoreProxy,
    child_env,
    events,
    finish,
    hooks_override,
    launch,
    make_step,
    manifests,
    probe_hook,
    s3_client,
    supervise_command,
    torchrun_pid,
    training,
    wait_for,
)

pytestmark = pytest.mark.slow

OUTAGE = 15.0
ITERATIONS = 100
PACE = 0.15
OVERRIDES = [
    hooks_override(probe_hook("PacingHook", seconds=PACE)),
    f"iterations={ITERATIONS}",
    "checkpoint.interval=10",
    "checkpoint.max_unsaved=30",  # the outage outlasts it: training holds, then goes on
    "checkpoint.retries=1",
    "storage.options.config_kwargs={connect_timeout: 2, read_timeout: 3}",
    "dist_timeout=20",
    "log.console=false",
]
OPTIONS = ["--nproc-per-node", "2", "--backoff-initial", "0.2", "--stop-grace", "3"]


def start(storage: str | Path, logs: Path, env: dict | None = None, more: list[str] = ()) -> subprocess.Popen:
    command = [sys.executable, "-m", "ftrain", "supervise", *OPTIONS, "configs/smoke.yaml", "--storage", str(storage)]
    output = open(f"{logs}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
    overrides = [*OVERRIDES, f"log_dir={logs}", *more]
    env = child_env({**(env or {}), "PYTHONPATH": str(TESTS)})
    return launch([*command, *overrides], cwd=REPO, env=env, stdout=output, stderr=subprocess.STDOUT)


@pytest.fixture
def reference(reference_state) -> str:
    """The state of the same run uninterrupted (the storage and its outages change nothing that is trained)."""
    return reference_state(ITERATIONS)


def wait_event(logs: Path, name: str) -> dict:
    return wait_for(lambda: next((e for e in events(logs) if e["event"] == name), None), f"a {name} event")


def assert_finished(proc: subprocess.Popen, outage, logs: Path, reference: str) -> list[dict]:
    """The run's events, once it has ended well: exit 0, no crash loop, the final step on S3 equal to the reference."""
    assert finish(proc, timeout=300) == 0, Path(f"{logs}.log").read_text()[-3000:]
    found = events(logs)
    names = [event["event"] for event in found]
    assert "usage" not in names and "crash_loop" not in names
    step, manifest = select_resume(Storage.open(outage.url, outage.options), log=lambda line: None)
    assert step == ITERATIONS and manifest["state_sha256"] == reference
    return found


def test_a_refusing_storage_with_a_worker_then_torchrun_killed_inside_the_outage_goes_on_from_the_spool(
    tmp_path, s3_outage, reference
):
    """A worker SIGKILLed deep into the outage (it cannot save) loses no more than the schedule's interval: between
    the storage's tries, which come further and further apart, the saves on the schedule went to the spool. Then
    torchrun is killed; both restarts go on from the spool while S3 still refuses."""
    logs = tmp_path / "logs"
    proc = start(s3_outage.url, logs, s3_outage.env, ["checkpoint.max_unsaved=1000"])  # no hold: training goes on
    beats = training(logs / "heartbeat", 20)
    s3_outage.server.refuse()
    began = time.monotonic()
    wait_for(lambda: "not committed" in Path(f"{logs}.log").read_text(), "a failed save")
    time.sleep(max(0.0, began + 3.5 - time.monotonic()))  # the storage was last tried 1-2 s ago, next in 2 s
    os.kill(beats[1].pid, signal.SIGKILL)
    recovered = wait_for(lambda: next((e for e in events(logs) if e["event"] == "recovered"), None), "a recovery")
    assert recovered["lost"] < 20, "the spool kept up with the schedule (every 10 iterations)"
    training(logs / "heartbeat", recovered["step"] + 5)
    os.kill(torchrun_pid(proc.pid), signal.SIGKILL)
    resumed = wait_for(
        lambda: re.findall(
            r"resumed from step (\d+) \(the spool .*: \S+ does not answer\)", Path(f"{logs}.log").read_text()
        )[1:],
        "two resumes from the spool while S3 refuses",
    )
    s3_outage.server.restore()  # both restarts went on from the spool while it refused (their lines say so)
    found = assert_finished(proc, s3_outage, logs, reference)
    assert "storage_wait" not in [event["event"] for event in found]
    assert [e["step"] for e in found if e["event"] == "recovered"] == [recovered["step"], int(resumed[0])]


@pytest.mark.parametrize("spool", [True, False])
def test_a_bucket_deleted_under_the_run_is_an_outage_not_bad_input(
    tmp_path, s3_server, s3_env, s3_url, reference, spool: bool
):
    """A bucket that never existed is bad input: the supervisor refuses it in one line and launches nothing. One
    deleted under a supervised run (emptied, then deleted, as S3 wants it) is an outage: the saves fail naming the
    bucket while training goes on; a worker killed meanwhile restarted into no bucket, called it bad input (exit 2)
    and ended the run. Now the restart goes on from the spool while the bucket is gone; without a spool it ends with
    exit 7 and the supervisor waits for the bucket, then starts over in it (its steps were deleted with it). Once
    the bucket is made again, the run ends on the uninterrupted bits."""
    url, options = s3_url
    bucket = url.split("/")[2]
    never = url.replace(bucket, f"{bucket}-never", 1)
    never = [sys.executable, "-m", "ftrain", "supervise", *OPTIONS, "configs/smoke.yaml", "--storage", never]
    refused = subprocess.run(never, cwd=REPO, env=child_env(s3_env), capture_output=True, text=True, timeout=120)
    assert refused.returncode == EXIT_USAGE and "Traceback" not in refused.stderr, refused.stderr
    assert f"S3 bucket '{bucket}-never' does not exist at " in refused.stderr, refused.stderr
    assert "launching torchrun" not in refused.stdout + refused.stderr

    logs = tmp_path / "logs"
    proc = start(url, logs, s3_env, ["checkpoint.max_unsaved=1000", f"checkpoint.spool={str(spool).lower()}"])
    beats = training(logs / "heartbeat", 20)
    client = s3_client(s3_server)
    _delete_bucket(client, bucket)
    gone = f"S3 bucket '{bucket}' at {s3_server['endpoint_url']} no longer exists"
    wait_for(lambda: gone in Path(f"{logs}.log").read_text(), "a failed save naming the bucket")
    os.kill(beats[1].pid, signal.SIGKILL)
    if spool:
        wait_for(lambda: "(the spool " in Path(f"{logs}.log").read_text(), "a resume from the spool")
    else:
        assert gone in wait_event(logs, "storage_wait")["cause"]
    client.create_bucket(Bucket=bucket)
    found = assert_finished(proc, types.SimpleNamespace(url=url, options=options), logs, reference)
    names = [event["event"] for event in found]
    if spool:
        assert [event["step"] >= 20 for event in found if event["event"] == "recovered"] == [True], found
    else:
        assert "storage_back" in names and "no verified checkpoint" in Path(f"{logs}.log").read_text()


def _delete_bucket(client: object, bucket: str) -> None:
    """Empties and deletes a bucket a run writes to: what it wrote meanwhile (BucketNotEmpty) goes in another round."""
    while True:
        for page in client.get_paginator("list_objects_v2").paginate(Bucket=bucket):
            for item in page.get("Contents", []):
                client.delete_object(Bucket=bucket, Key=item["Key"])
        try:
            client.delete_bucket(Bucket=bucket)
            return
        except botocore.exceptions.ClientError as error:
            if error.response["Error"]["Code"] != "BucketNotEmpty":
                raise


@pytest.mark.waits
def test_a_hanging_storage_with_a_worker_killed_inside_the_outage_is_waited_out_without_a_spool(
    tmp_path, s3_outage, reference
):
    logs = tmp_path / "logs"
    proc = start(s3_outage.url, logs, s3_outage.env, ["checkpoint.spool=false"])
    beats = training(logs / "heartbeat", 20)
    s3_outage.server.hang()
    began = time.monotonic()
    time.sleep(2)
    os.kill(beats[1].pid, signal.SIGKILL)
    wait_event(logs, "storage_wait")
    time.sleep(max(0.0, began + OUTAGE - time.monotonic()))
    s3_outage.server.unhang()
    names = [event["event"] for event in assert_finished(proc, s3_outage, logs, reference)]
    assert "storage_wait" in names and "storage_back" in names


@pytest.mark.waits
def test_an_upload_that_is_never_answered_is_given_up_and_training_goes_on_through_it(
    tmp_path, s3_server, s3_env, s3_url, reference
):
    """A server that takes an upload and never answers (one paused in the middle of a save) held the PUT for as long
    as it stayed so: aiohttp's read timeout starts only once a request's body is sent, and the body waited for ``100
    Continue``. The saves in flight stopped, then the training behind them, with no line and a heartbeat that kept
    beating. Each S3 request has a deadline now: the saves fail, training goes on (to the spool) while every PUT
    stalls, and the run ends on the uninterrupted bits. Before the deadlines (a read timeout of 10 s here), training
    goes on too: a save due while two are in flight waited for the oldest, which froze the loop for as long as a
    request's deadlines (a minute at the default timeouts); it is left to a later boundary now."""
    url, options = s3_url
    proxy = StoreProxy(s3_server["endpoint_url"])
    try:
        logs = tmp_path / "logs"
        env = {**s3_env, "AWS_ENDPOINT_URL": proxy.endpoint_url}
        slow = "storage.options.config_kwargs={connect_timeout: 2, read_timeout: 10}"
        proc = start(url, logs, env, ["checkpoint.max_unsaved=1000", slow])  # no hold: training goes on
        training(logs / "heartbeat", 20)
        proxy.stalling.set()
        try:
            stalled_at = max(beat.iteration for beat in read_heartbeats(logs / "heartbeat").values())
            rank_0 = lambda: read_heartbeats(logs / "heartbeat").get(0)  # noqa: E731
            wait_for(lambda: rank_0().iteration >= stalled_at + 25, "training past two saves due, two in flight")
            assert "not committed" not in Path(f"{logs}.log").read_text()  # nor had they failed yet
            wait_for(lambda: "not committed" in Path(f"{logs}.log").read_text(), "a failed save", timeout=60)
            held = f"training held at step {ITERATIONS}"  # trained to the end while every PUT stalls: the last save
            wait_for(lambda: held in Path(f"{logs}.log").read_text(), "the last save held", timeout=120)
        finally:
            proxy.stalling.clear()
        assert_finished(proc, types.SimpleNamespace(url=url, options=options), logs, reference)
    finally:
        proxy.close()


MOUNT_OUTAGE = 9.0
MOUNT_ITERATIONS = 8


@pytest.mark.waits
def test_a_failing_mount_is_waited_out(tmp_path, reference_state):
    """A storage on a FUSE mount of the test's own that answers every operation with EIO for ``MOUNT_OUTAGE`` s, as a
    hung NFS or FUSE mount does, from iteration 4 of 8 (``Hold``): the saves fail while training goes on, the last one
    holds; a worker killed meanwhile restarts into the outage (exit 7), which the supervisor waits out. The logs go off
    the mount (a local storage's log directory is the storage itself)."""
    logs = tmp_path / "logs"
    hold = Hold(tmp_path, 4)
    with failing_mount(tmp_path / "fuse") as mount:
        command = [sys.executable, "-m", "ftrain", "supervise", *OPTIONS, "configs/smoke.yaml"]
        overrides = [hold.override, f"iterations={MOUNT_ITERATIONS}", "checkpoint.retries=1", "dist_timeout=20"]
        output = open(f"{logs}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
        proc = launch(
            [*command, "--storage", str(mount.path / "run"), *overrides, "log.console=false", f"log_dir={logs}"],
            cwd=REPO,
            env=child_env({"PYTHONPATH": str(TESTS)}),
            stdout=output,
            stderr=subprocess.STDOUT,
        )
        hold.held()
        mount.fail()
        began = time.monotonic()
        hold.release()
        wait_for(lambda: "training held" in Path(f"{logs}.log").read_text(), "the last save holding")
        os.kill(read_heartbeats(logs / "heartbeat")[1].pid, signal.SIGKILL)
        wait_event(logs, "storage_wait")
        time.sleep(max(0.0, began + MOUNT_OUTAGE - time.monotonic()))
        mount.recover()
        assert finish(proc, timeout=300) == 0, Path(f"{logs}.log").read_text()[-3000:]
        step, manifest = select_resume(Storage.open(str(mount.path / "run")), log=lambda line: None)
    assert step == MOUNT_ITERATIONS and manifest["state_sha256"] == reference_state(MOUNT_ITERATIONS)
    names = [event["event"] for event in events(logs)]
    assert "storage_wait" in names and "storage_back" in names and names[-2:] == ["done", "summary"], names
    assert "not committed" in Path(f"{logs}.log").read_text()


@contextlib.contextmanager
def small_disk(mountpoint: Path, size: str, inodes: int | None = None) -> Iterator[Path]:
    """A tmpfs of ``size`` (and ``inodes``, if given) at ``mountpoint``: a real file system that fills up; unmounted at
    the end. Skips where one cannot be mounted (not root, no permission to mount)."""
    mountpoint.mkdir()
    if os.geteuid() != 0 or not shutil.which("mount"):
        pytest.skip("mounting a tmpfs takes root and mount(8)")
    options = f"size={size}" + (f",nr_inodes={inodes}" if inodes else "")
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(mountpoint)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode(errors='replace').strip()}")
    try:
        yield mountpoint
    finally:
        subprocess.run(["umount", "-l", str(mountpoint)], capture_output=True)


def fill(disk: Path) -> Path:
    """Fill ``disk`` to its last byte with one file, which the test deletes to give the space back."""
    filler = disk / "filler"
    with open(filler, "wb", buffering=0) as file, contextlib.suppress(OSError):
        while True:
            file.write(bytes(1 << 16))
    assert shutil.disk_usage(disk).free == 0
    return filler


@pytest.mark.waits
def test_a_full_disk_is_waited_out_and_the_run_ends_on_the_uninterrupted_bits(tmp_path, reference_state):
    """The storage and its logs (the default layout) on a small disk, filled to its last byte at iteration 4 of 8
    (``Hold``): the workers cannot write (their heartbeats, their error files neither) and end; the supervisor finds
    the disk full and waits for space, where it restarted into the full disk until the crash loop ended the run. Once
    the filler is deleted, the run goes on and ends on an uninterrupted run's bits."""
    output, hold = tmp_path / "supervise.log", Hold(tmp_path, 4)
    with small_disk(tmp_path / "disk", "8m") as disk:
        filler = fill(disk)  # first, without a supervisor, on the full disk: one line, exit 7
        refused = subprocess.run(
            [sys.executable, "-m", "ftrain", "train", "configs/smoke.yaml", "--storage", str(disk / "alone")],
            cwd=REPO,
            env=child_env(),
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert refused.returncode == 7 and refused.stderr.startswith("ftrain: error: no space left"), refused.stderr
        assert "Traceback" not in refused.stderr and "free space there" in refused.stderr
        filler.unlink()

        command = [sys.executable, "-m", "ftrain", "supervise", *OPTIONS, "configs/smoke.yaml"]
        overrides = [hold.override, f"iterations={MOUNT_ITERATIONS}", "log.console=false", "dist_timeout=20"]
        with output.open("ab") as log:
            proc = launch(
                [*command, "--storage", str(disk / "run"), *overrides],
                cwd=REPO,
                env=child_env({"PYTHONPATH": str(TESTS)}),
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        hold.held()
        filler = fill(disk)
        hold.release()
        wait_for(lambda: "no space left for" in output.read_text(), "the supervisor waiting for space")
        time.sleep(3)  # waiting, not restarting into the full disk
        assert "restart 1" not in output.read_text() and proc.poll() is None, output.read_text()[-3000:]
        filler.unlink()
        assert finish(proc, timeout=300) == 0, output.read_text()[-3000:]
        step, manifest = select_resume(Storage.open(str(disk / "run")), log=lambda line: None)
        names = [event["event"] for event in events(disk / "run")]
    assert step == MOUNT_ITERATIONS and manifest["state_sha256"] == reference_state(MOUNT_ITERATIONS)
    assert "storage_back" in names and "crash_loop" not in names and names[-2:] == ["done", "summary"], names


def test_a_disk_out_of_inodes_with_bytes_to_spare_is_full(tmp_path) -> None:
    """Free bytes alone would let the supervisor restart into a disk that takes no new file (a quota does the same):
    the probe writes, and only a disk that takes the write has room."""
    with small_disk(tmp_path / "disk", "8m", inodes=32) as disk:
        storage = Storage.open(str(disk / "run"))
        assert short_of_space(storage, [], tmp_path / "logs") is None
        files = 0
        with contextlib.suppress(OSError):
            while True:
                (disk / f"empty-{files}").touch()
                files += 1
        print(f"the disk took {files} empty files, {shutil.disk_usage(disk).free} bytes left free")
        assert shutil.disk_usage(disk).free > 7 << 20
        assert "write fails: No space left on device" in short_of_space(storage, [], None)
        (disk / "empty-0").unlink()
        assert short_of_space(storage, [], None) is None


def test_the_space_probe_leaves_no_file_behind_when_its_process_is_killed(tmp_path) -> None:
    """The supervisor writes a probe into the run's disks while it waits: killed then (SIGKILL, at random moments of
    a loop of probes), it leaves no probe file in the user's directory."""
    probing = "import sys\nfrom pathlib import Path\nfrom ftrain.supervise.outage import _write_fails\n"
    probing += "print('probing', flush=True)\nwhile True:\n    _write_fails(Path(sys.argv[1]))\n"
    draw, kills = random.Random(9), 6
    for _ in range(kills):
        child = subprocess.Popen(
            [sys.executable, "-c", probing, str(tmp_path)], env=child_env(), stdout=subprocess.PIPE
        )
        assert child.stdout.readline() == b"probing\n"
        time.sleep(draw.uniform(0.05, 0.3))
        child.kill()
        child.wait()
    assert list(tmp_path.iterdir()) == [], f"left after {kills} kills"


def test_a_full_disk_is_named_with_the_fix_for_what_lies_on_it(tmp_path) -> None:
    """Logs alone on a full disk: free space there (keeping fewer checkpoints would not help); the storage on it:
    that, or keep fewer checkpoints."""
    with small_disk(tmp_path / "disk", "2m") as disk:
        fill(disk)
        elsewhere = Storage.open(str(tmp_path / "run"))
        logs = short_of_space(elsewhere, [], disk / "logs")
        assert logs.startswith(f"no space left for {disk / 'logs'}: ") and logs.endswith(
            "(the run's logs and heartbeats): free space there"
        ), logs
        on_disk = short_of_space(Storage.open(str(disk / "run")), [], disk / "run")
        assert on_disk.endswith("free space there, or keep fewer checkpoints (checkpoint.keep_last)"), on_disk


@pytest.mark.parametrize("command", ["train", "prune"])
def test_a_read_only_storage_is_bad_input_in_one_line(tmp_path, command) -> None:
    """A storage remounted read-only (as a disk is after errors) is bad input, as the supervisor's probe says (exit
    2), not a raw EROFS (exit 1), for a run (its checkpoints/ tried first) and for ``ckpt prune``, which takes the
    storage's lock."""
    with small_disk(tmp_path / "disk", "1m") as disk:
        make_step(Storage.open(str(disk)), 4)
        subprocess.run(["mount", "-o", "remount,ro", str(disk)], check=True)
        words = ["ckpt", "prune", str(disk)]
        if command == "train":
            words = ["train", SMOKE, "--storage", str(disk), "iterations=8", f"log_dir={tmp_path / 'logs'}"]
        result = subprocess.run(
            [sys.executable, "-m", "ftrain", *words], env=child_env(), capture_output=True, text=True
        )
    assert result.returncode == EXIT_USAGE and len(result.stderr.strip().splitlines()) == 1, result.stderr
    if command == "train":  # its checkpoints/ is tried before the run starts
        assert result.stderr == (
            f"ftrain: error: cannot write {disk / 'checkpoints'} (it takes no new file: Read-only file system): make "
            "it writable (its permissions, its mount), or pass --storage another directory\n"
        )
    else:
        assert result.stderr.startswith("ftrain: error: lock ")
        assert "read-only file system: pass a storage you can write to" in result.stderr, result.stderr


def test_a_file_where_the_last_step_goes_is_named_while_training_holds_and_once_moved_the_run_ends(tmp_path) -> None:
    """A stray file named as the step a supervised run saves last (``checkpoints/step-000000008``): the save was
    "does not exist", and the hold said to "run the same command again once it is back", which could not help. The
    hold names the file and the fix; moved away, the next try lands and the run ends with every step, no restart."""
    storage = tmp_path / "run"
    (storage / "checkpoints").mkdir(parents=True)
    stray = storage / "checkpoints" / "step-000000008"
    stray.write_text("notes\n")
    command = supervise_command(storage, "iterations=8", "checkpoint.interval=2", "log.console=true")
    proc = launch(command, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    told = f"{stray} is a file where ftrain needs a directory: move it out of the storage"
    try:
        seen = []
        for line in proc.stdout:
            seen.append(line)
            if "training held at step 8" in line:
                break
        assert told in seen[-1], seen
        failed = [line for line in seen if "checkpoint step 8 not committed" in line]
        assert failed and all("training is done, and the run retries this last step" in line for line in failed), seen
        stray.rename(tmp_path / "notes.txt")
        rest = proc.communicate(timeout=120)[0]
    finally:
        proc.kill()  # a failure here leaves no supervisor holding for the storage wait
    assert proc.returncode == 0, rest[-2000:]
    assert sorted(manifests(storage)) == [4, 6, 8] and (tmp_path / "notes.txt").read_text() == "notes\n"
    assert "0 restarts" in rest and "Traceback" not in rest, rest[-2000:]


def test_a_checkpoints_directory_that_takes_no_write_is_bad_input_not_an_outage(tmp_path) -> None:
    """A storage that lists but cannot be written (here made immutable: root ignores modes) would pass a listing probe,
    and the supervisor would restart into failing saves without end: the probe writes, and says so in one line."""
    (tmp_path / "run" / "checkpoints").mkdir(parents=True)
    if not shutil.which("chattr") or subprocess.run(["chattr", "+i", str(tmp_path / "run/checkpoints")]).returncode:
        pytest.skip("chattr +i is not available here")
    try:
        with pytest.raises(UserError, match=r"cannot write in .*/run/checkpoints \(Operation not permitted\)"):
            probe(str(tmp_path / "run"), None, tmp_path / "logs")
    finally:
        subprocess.run(["chattr", "-i", str(tmp_path / "run/checkpoints")])
    assert probe(str(tmp_path / "run"), None, tmp_path / "logs") is None
