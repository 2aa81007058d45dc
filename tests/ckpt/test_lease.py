"""The storage lease on a local directory and on a real S3 API server: refused while another run lives, taken over
at once from a dead process of this host, after the expiry from another host, shared by the nodes of one run."""

from __future__ import annotations

import dataclasses
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import threading
import time

import pytest

from ftrain.ckpt import cas
from ftrain.ckpt.claim import claim
from ftrain.ckpt.fence import Fence
from ftrain.ckpt.lease import LEASE, Entry, Lease, LeaseHeld, LeaseLost, Record
from ftrain.ckpt.storage import Storage
from ftrain.config import Config, load_config
from ftrain.errors import UserError
from ftrain.identity import GENERATION_ENV, RUN_ID_ENV, Identity
from ftrain.log_dir_lock import claim_log_dir
from ftrain.procfs import Process

from helpers import SMOKE, child_env, wait_for

RACER = textwrap.dedent(
    """
    import json, sys
    from ftrain.ckpt.lease import Lease, LeaseHeld
    from ftrain.ckpt.storage import Storage
    url, options, run = sys.argv[1], json.loads(sys.argv[2]), sys.argv[3]
    lease = Lease(Storage.open(url, options), run, print)
    print("ready", flush=True)
    sys.stdin.readline()  # go: every racer is ready
    try:
        lease.acquire()
        print("won", flush=True)
    except LeaseHeld:
        print("refused", flush=True)
    sys.stdin.read()  # stay alive while the others look (a live holder), until the test has every outcome
    """
)
HOLDER = textwrap.dedent(
    """
    import json, sys, time
    from ftrain.ckpt.lease import Lease
    from ftrain.ckpt.storage import Storage
    url, options = sys.argv[1], json.loads(sys.argv[2])
    Lease(Storage.open(url, options), "first-run", print, ttl=float(sys.argv[3])).hold()
    print("held", flush=True)
    time.sleep(600)
    """
)


@pytest.fixture(params=["local", "s3"])
def storage(request, tmp_path) -> Storage:
    if request.param == "local":
        return Storage.open(str(tmp_path / "run"))
    url, options = request.getfixturevalue("s3_url")
    return Storage.open(url, options)


def open_again(storage: Storage) -> tuple[str, dict]:
    """``(url, options)`` that open ``storage`` in another process."""
    if storage.is_local:
        return storage.url, {}
    endpoint = storage.fs.client_kwargs.get("endpoint_url") or storage.fs.endpoint_url
    return storage.url, {"endpoint_url": endpoint, "key": storage.fs.key, "secret": storage.fs.secret}


@pytest.fixture
def holder(storage):
    """Another process holding ``storage``'s lease for run ``first-run`` (renewing it every 2 s)."""
    url, options = open_again(storage)
    proc = subprocess.Popen(
        [sys.executable, "-c", HOLDER, url, json.dumps(options), "6"],
        env=child_env(),
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout.readline().strip() == "held"
        yield proc
    finally:
        proc.kill()
        proc.wait()


def foreign(run_id: str, renewed_at: float, ttl: float = 60.0, generation: int = 4) -> Record:
    """A lease record of a process on another host, renewed at ``renewed_at``."""
    process = Process("node-far-away", 4242, 123, "another-boot-id", "pid:[1]")
    return Record(run_id, generation, ttl, (Entry(process, renewed_at),))


def record(storage: Storage) -> Record:
    return Record.decode(storage.read(LEASE))


def test_refused_while_another_process_holds_it_then_taken_over_at_once_when_it_dies(storage, holder):
    second = Lease(storage, "second-run", print)
    with pytest.raises(LeaseHeld) as refused:
        second.acquire()
    message = str(refused.value)
    assert "\n" not in message
    assert "first-run" in message and f"pid {holder.pid} on host " in message and "ends at " in message
    assert record(storage).run_id == "first-run"  # nothing of the first run was touched

    holder.send_signal(signal.SIGKILL)
    holder.wait()
    started = time.monotonic()
    taken = second.acquire()
    assert time.monotonic() - started < 20  # the dead pid is seen at once: no waiting for the 60 s expiry
    assert taken is not None and f"pid {holder.pid} on host" in taken and "is gone" in taken and "first-run" in taken
    now = record(storage)
    assert now.run_id == "second-run" and now.generation == 2
    assert [e.process.pid for e in now.entries] == [os.getpid()]


@pytest.mark.waits
@pytest.mark.slow
def test_a_stopped_holder_on_this_host_keeps_the_lease_past_its_end_and_the_refusal_says_so(storage, holder):
    """SIGSTOP: no renewal, but the process lives, and may go on at any moment: its lease is not taken."""
    holder.send_signal(signal.SIGSTOP)
    try:
        time.sleep(7)  # past the holder's 6 s time to live
        with pytest.raises(LeaseHeld) as refused:
            Lease(storage, "second-run", print).acquire()
        message = str(refused.value)
        assert re.search(
            r"its lease ran out at .+ UTC, but its process still exists on this host and keeps it; stop", message
        )
        assert record(storage).run_id == "first-run", message
    finally:
        holder.send_signal(signal.SIGCONT)


@pytest.mark.waits
@pytest.mark.slow
def test_of_processes_that_race_for_a_free_lease_exactly_one_wins(storage):
    url, options = open_again(storage)
    racers = [
        subprocess.Popen(
            [sys.executable, "-c", RACER, url, json.dumps(options), f"run-{n}"],
            env=child_env(),
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        for n in range(4)
    ]
    assert [racer.stdout.readline().strip() for racer in racers] == ["ready"] * 4  # imported, the storage open
    for racer in racers:
        racer.stdin.write("go\n")
        racer.stdin.flush()
    outcomes = [racer.stdout.readline().strip() for racer in racers]
    for racer in racers:
        racer.communicate(timeout=60)
    assert sorted(outcomes) == ["refused", "refused", "refused", "won"]
    assert record(storage).run_id == f"run-{outcomes.index('won')}"


@pytest.mark.waits
@pytest.mark.parametrize("skew", [-300.0, 3e9], ids=["behind", "ahead"])
def test_a_lease_of_another_host_holds_until_it_expires_by_the_storages_clock(storage, skew):
    """Another host's clock is 5 minutes behind, or a century ahead (or its record was edited so): its renewal's own
    time says expired, or held for a century; the storage's clock decides: held while it was written within the ttl,
    taken once it was not."""
    storage.write_replace(LEASE, foreign("far-run", time.time()).encode())
    with pytest.raises(LeaseHeld, match="far-run, pid 4242 on host node-far-away"):
        Lease(storage, "mine", print).acquire()

    storage.write_replace(LEASE, foreign("far-run", time.time() + skew, ttl=30.0).encode())  # 30: a slow storage too
    with pytest.raises(LeaseHeld, match="far-run, pid 4242 on host node-far-away") as refused:
        Lease(storage, "mine", print).acquire()
    said = "ahead of this one's; the storage's" if skew > 0 else "by its host's clock, but the storage's"
    assert f"{said} clock says it is still renewed" in str(refused.value)
    storage.write_replace(LEASE, foreign("far-run", time.time() + skew, ttl=3.0).encode())
    time.sleep(4.5)  # no renewal for longer than its ttl, by the storage's clock (whole seconds on S3)
    taken = Lease(storage, "mine", print).acquire()
    said = "ahead of this one's; by the storage's clock it expired" if skew > 0 else "expired at"
    assert taken is not None and "from run far-run" in taken and said in taken, taken
    assert record(storage).run_id == "mine" and record(storage).generation == 5


def test_a_lease_file_dated_in_the_storages_future_is_no_renewal(tmp_path):
    """A storage copied with its times kept (``cp -a``, ``rsync -a``) from a host whose clock ran ahead, or a touch:
    the lease file looks written years from now, which said 'still renewed' until then (no run could start)."""
    storage = Storage.open(str(tmp_path / "run"))
    storage.write_replace(LEASE, foreign("far-run", time.time() - 1000, ttl=30.0).encode())
    ahead = time.time() + 10 * 365 * 86400
    os.utime(tmp_path / "run" / LEASE, (ahead, ahead))
    taken = Lease(storage, "mine", print).acquire()
    assert taken is not None and "from run far-run" in taken and "expired at" in taken, taken
    storage.write_replace(LEASE, foreign("far-run", time.time() - 1000, ttl=30.0).encode())
    os.utime(tmp_path / "run" / LEASE, (time.time() + 5, time.time() + 5))  # a few seconds: another clock's skew
    with pytest.raises(LeaseHeld, match="the storage's clock says it is still renewed"):
        Lease(storage, "mine", print).acquire()


def test_every_node_of_one_run_is_admitted_and_renews_its_own_entry(storage):
    storage.write_replace(LEASE, foreign("shared-run", time.time()).encode())
    lease = Lease(storage, "shared-run", print, shared=True)
    assert lease.acquire() is None
    pids = sorted(e.process.pid for e in record(storage).entries)
    assert pids == sorted([4242, os.getpid()])
    assert record(storage).generation == 4  # the same run: the same generation

    lease.release()  # the other node still lives: the lease stays, without this node
    assert [e.process.pid for e in record(storage).entries] == [4242]
    with pytest.raises(LeaseHeld):
        Lease(storage, "another-run", print).acquire()


def test_a_second_start_of_a_run_id_is_refused_while_the_first_runs_on_this_host(storage, holder):
    """Two launches that share a run id (one FTRAIN_RUN_ID, one --rdzv-id) are not nodes of one run: the second is
    refused in one line naming the first, which keeps its generation and its entry; only the supervisors of one
    run's nodes (``shared``) join each other's."""

    def holders(record: Record) -> tuple:  # the holder renews meanwhile: what changes then is not compared
        return record.run_id, record.generation, [(e.process, e.since) for e in record.entries]

    before = record(storage)
    with pytest.raises(LeaseHeld) as refused:
        Lease(storage, "first-run", print).acquire()
    message = str(refused.value)
    assert "\n" not in message and f"another start of run first-run (pid {holder.pid} on host " in message, message
    assert holders(record(storage)) == holders(before)  # not joined, not taken
    node = Lease(storage, "first-run", print, shared=True)
    assert node.acquire() is None and node.generation == before.generation
    assert sorted(e.process.pid for e in record(storage).entries) == sorted([holder.pid, os.getpid()])


def test_a_second_start_of_a_run_id_takes_the_next_generation_from_another_hosts(storage):
    """Seen only by its renewals, another host's entry of this run id may be the run's own old holder on a host it
    left (a restart elsewhere): the new start takes the next generation, says so, and the old one is fenced off."""
    storage.write_replace(LEASE, foreign("job-7", time.time()).encode())
    lease = Lease(storage, "job-7", print)
    taken = lease.acquire()
    assert taken is not None and "from an earlier start of run job-7: pid 4242 on host node-far-away held it" in taken
    assert (record(storage).generation, [e.process.pid for e in record(storage).entries]) == (5, [os.getpid()])
    with pytest.raises(LeaseLost, match="newer start of run job-7"):
        Fence(storage, Identity("job-7", 4)).check()


def test_release_lets_the_next_run_start_at_once_at_the_next_generation(storage):
    first = Lease(storage, "first", print)
    assert first.hold() is None
    assert (record(storage).run_id, record(storage).generation) == ("first", 1)
    assert (os.environ[RUN_ID_ENV], os.environ[GENERATION_ENV]) == ("first", "1")  # for its commits and workers
    first.release()
    assert record(storage).entries == ()  # no holder; the generation stays, so that it only grows
    assert "expires" not in json.loads(storage.read(LEASE))  # not 1970: nothing to expire
    assert Lease(storage, "second", print).acquire() is None  # nothing said: nobody held it
    assert (record(storage).run_id, record(storage).generation) == ("second", 2)


def test_a_write_from_a_stale_read_is_refused_by_the_storage(storage):
    Lease(storage, "first", print).acquire()
    stale = cas.read(storage, LEASE)
    assert stale is not None and Record.decode(stale[0]).run_id == "first"
    storage.write_replace(LEASE, foreign("other", time.time()).encode())  # someone else wrote it since
    with pytest.raises(cas.Conflict):
        cas.write(storage, LEASE, foreign("mine", time.time()).encode(), stale[1])
    with pytest.raises(cas.Conflict):
        cas.write(storage, LEASE, foreign("mine", time.time()).encode(), None)  # create: it exists
    assert record(storage).run_id == "other"
    current = cas.read(storage, LEASE)
    cas.write(storage, LEASE, foreign("mine", time.time()).encode(), current[1])
    assert record(storage).run_id == "mine"


def test_a_lease_deleted_under_its_holder_is_written_again_and_said(storage):
    """The storage deleted under a run (its checkpoints, the lease with them): the renewal wrote the record again in
    silence, and the run went on as if nothing had gone."""
    lease = Lease(storage, "mine", print)
    lease.acquire()
    if storage.is_local:
        shutil.rmtree(storage.url)  # the whole storage
    else:
        storage.delete(LEASE)
    said = lease.renew()
    assert said == (
        f"the lease {storage.where(LEASE)} was gone (deleted under the run, maybe with the storage's checkpoints): "
        "written again, generation 1"
    ), said
    assert (record(storage).run_id, record(storage).generation) == ("mine", 1) and lease.renew() is None


def test_a_lease_taken_by_another_run_is_lost_for_good_and_said_once(storage):
    lease = Lease(storage, "mine", print)
    lease.acquire()
    assert lease.renew() is None and record(storage).generation == 1  # renewed, nothing to say
    storage.write_replace(LEASE, foreign("intruder", time.time(), generation=2).encode())  # taken during an outage
    lost = lease.renew()
    assert lost is not None and "taken by run intruder (generation 2; this run's is 1)" in lost, lost
    assert lease.lost == lost and lease.renew() is None  # said once
    storage.write_replace(LEASE, foreign("intruder", time.time() - 100, generation=2).encode())  # and it lapsed
    assert lease.renew() is None and record(storage).run_id == "intruder"  # never taken back: two writers


@pytest.mark.waits
def test_a_run_id_started_again_when_none_of_its_processes_lives_fences_off_the_old_ones(storage):
    """A batch job keeps its run id across a requeue: the requeued job is a new holder, and what the old one still
    has running (a node paused past the expiry, as another host sees it) commits nothing more."""
    storage.write_replace(LEASE, foreign("job-42", time.time(), generation=4).encode())
    old = Lease(storage, "job-42", print, shared=True)
    assert old.acquire() is None and record(storage).generation == 4  # a node of the live run joins it
    storage.write_replace(LEASE, foreign("job-42", time.time() - 61, ttl=2.0, generation=4).encode())
    time.sleep(3.5)  # every process of the job has stopped renewing (by the storage's clock too)
    requeued = Lease(storage, "job-42", print, ttl=3.0, shared=True)  # looks again after a third of its ttl: expired
    assert requeued.acquire() is None
    assert (record(storage).generation, [e.process.pid for e in record(storage).entries]) == (5, [os.getpid()])
    lost = old.renew()
    assert lost is not None and "taken by a newer start of run job-42 (generation 5; this one's is 4)" in lost, lost
    with pytest.raises(LeaseLost, match="newer start of run job-42"):
        Fence(storage, Identity("job-42", 4)).check()
    assert Fence(storage, Identity("job-42", 5)).check() == {"run_id": "job-42", "generation": 5}  # the requeued job


def test_a_new_plan_takes_the_next_generation_and_the_nodes_that_follow_plans_are_not_lost(storage):
    """Node 0's supervisor started again on c10d (or a run started anew on etcd) makes a new plan: it takes the next
    generation, keeping the run's live nodes, which follow the plan and renew on. A process alone (one node, node
    0 itself) that finds the newer generation has lost the storage."""

    def elsewhere(lease: Lease, pid: int) -> Lease:  # a process of another host: seen by its renewals only
        lease.process = Process("node-far-away", pid, 123, "another-boot-id", "pid:[1]")
        return lease

    follower = elsewhere(Lease(storage, "shared-run", print, follows=True), 1)
    alone = elsewhere(Lease(storage, "shared-run", print, shared=True), 2)
    assert follower.acquire() is None and alone.acquire() is None and record(storage).generation == 1
    maker = Lease(storage, "shared-run", print, shared=True)
    assert maker.hold(advance=True) is None
    assert (maker.generation, os.environ[GENERATION_ENV]) == (2, "2")
    assert sorted(e.process.pid for e in record(storage).entries) == sorted([1, 2, os.getpid()])  # nobody dropped
    assert follower.renew() is None and follower.lost is None and record(storage).generation == 2
    assert "newer start of run shared-run (generation 2; this one's is 1)" in alone.renew()
    assert maker.advance(2) == (3, True) and follower.renew() is None and record(storage).generation == 3
    assert maker.advance(2) == (3, False)  # another process of the run advanced from 2 first: no generation 4
    with pytest.raises(LeaseHeld):
        Lease(storage, "another-run", print).acquire()
    follower.release()  # a follower drops its entry from the newer generation's record too
    assert 1 not in [e.process.pid for e in record(storage).entries]
    maker.release()


@pytest.mark.waits
def test_a_node_starting_after_an_outage_joins_the_nodes_of_its_run_that_renew_again(storage, monkeypatch):
    """After an outage longer than the ttl every entry of another host looks expired; a node of the same run that
    starts then looks again after a third of the ttl, finds them renewed, and joins their generation instead of
    fencing them off. The other node renews while this one waits (its wait is where it happens, not a sleep of the
    test's own: a loaded machine once let that sleep run past the third of the ttl)."""
    storage.write_replace(LEASE, foreign("shared-run", time.time() - 61, ttl=3.0, generation=4).encode())
    time.sleep(3.5)  # expired by the storage's clock too
    waits: list[float] = []
    sleep = time.sleep

    def wait_while_the_other_node_renews(seconds: float) -> None:
        if threading.current_thread() is not threading.main_thread():  # the S3 server's own threads
            return sleep(seconds)
        waits.append(seconds)
        storage.write_replace(LEASE, foreign("shared-run", time.time(), ttl=3.0, generation=4).encode())
        sleep(seconds)

    monkeypatch.setattr(time, "sleep", wait_while_the_other_node_renews)
    lease = Lease(storage, "shared-run", print, ttl=3.0, shared=True)
    assert lease.acquire() is None
    assert waits == [1.0]  # looked again once, after a third of the ttl
    assert (lease.generation, record(storage).generation) == (4, 4)
    assert sorted(e.process.pid for e in record(storage).entries) == sorted([4242, os.getpid()])


def test_only_this_hosts_own_processes_are_seen_gone():
    here = Process.current()
    assert here.running() is True
    assert dataclasses.replace(here, start=here.start + 1).running() is False  # its pid, another process: gone
    # a host of this name with another boot id: a clone of this machine (or this one rebooted): left to the expiry
    assert dataclasses.replace(here, boot="another-boot-id").running() is None


def test_a_commit_of_a_run_whose_lease_another_run_took_is_refused(storage):
    mine = Lease(storage, "mine", print)
    mine.hold()
    token = Fence.from_env(storage)
    assert token.identity == Identity("mine", 1)
    token.check()  # still ours
    mine.release()
    token.check()  # released, nobody took it: the run's own last commits (the supervisor releases last)
    other = Lease(storage, "other", print)
    other.acquire()
    with pytest.raises(LeaseLost, match=r"taken by run other \(generation 2; this run's is 1\): this run lost"):
        token.check()


def test_the_keeper_renews_and_outlives_a_failing_storage(tmp_path):
    storage = Storage.open(str(tmp_path / "run"), retries=0)
    said: list[str] = []
    lease = Lease(storage, "mine", said.append, ttl=0.6)
    lease.hold()
    first = record(storage).entries[0].renewed_at
    wait_for(lambda: record(storage).entries[0].renewed_at > first, "a renewal", timeout=10)

    os.remove(tmp_path / "run" / LEASE)
    os.mkdir(tmp_path / "run" / LEASE)  # the storage now fails every read of the lease
    wait_for(lambda: any("renewing the lease" in line for line in said), "a failed renewal logged", timeout=10)
    assert lease._thread.is_alive()
    time.sleep(0.5)  # several failed renewals: still one line
    assert len([line for line in said if "renewing the lease" in line]) == 1
    os.rmdir(tmp_path / "run" / LEASE)
    wait_for(lambda: any("renewed the lease again after" in line for line in said), "the renewal back", timeout=10)
    assert record(storage).run_id == "mine"
    lease.release()
    lease._thread.join(timeout=30)  # release waits a third of the ttl for a renewal in flight, not always enough here
    assert not lease._thread.is_alive() and record(storage).entries == ()


def test_a_renewal_in_flight_when_the_lease_is_released_does_not_write_the_entry_back(tmp_path, monkeypatch):
    """``release`` waits a third of the ttl for a renewal in flight (a hanging request), then drops the entry; the
    renewal's write, made against the record before the drop, is refused, and it must give up rather than read
    again and write the released entry back (a process gone, seen live on other hosts until its ttl ran out)."""
    storage = Storage.open(str(tmp_path / "run"))
    lease = Lease(storage, "mine", print, ttl=0.6)
    lease.hold()
    write, in_flight, dropped = cas.write, threading.Event(), threading.Event()

    def write_held_up_in_the_keeper(storage: Storage, rel: str, data: bytes, version: str | None) -> None:
        if threading.current_thread() is lease._thread and not dropped.is_set():
            in_flight.set()
            dropped.wait(timeout=30)  # the request hangs until release has dropped the entry
        write(storage, rel, data, version)
        if threading.current_thread() is threading.main_thread():
            dropped.set()

    monkeypatch.setattr(cas, "write", write_held_up_in_the_keeper)
    assert in_flight.wait(timeout=30)
    lease.release()
    lease._thread.join(timeout=30)
    assert not lease._thread.is_alive() and dropped.is_set()
    assert record(storage).entries == ()


@pytest.mark.parametrize("data", [b"{not json", b"\xff\xfe", b"[" * 5000 + b"]" * 5000], ids=["cut", "bytes", "deep"])
def test_an_unreadable_lease_is_bad_input_and_left_alone(storage, data):
    storage.write_replace(LEASE, data)
    with pytest.raises(
        UserError, match=r"LEASE.json is not a lease ftrain can read \(not JSON\): if no run uses this storage"
    ):
        Lease(storage, "mine", print).acquire()
    assert storage.read(LEASE) == data


def test_a_lease_with_any_field_damaged_is_bad_input_in_one_line_and_left_alone(tmp_path):
    """Generated cases: every field of a real lease record (a holder's too) given each of a set of wrong values (another
    type, a float where a whole number goes, out of range, missing): one line naming the file and the field, the record
    untouched;
    never a traceback, and never a generation below 1 or past a float's precision taken (every commit of the run
    would be set aside as superseded at its next start)."""
    storage = Storage.open(str(tmp_path / "run"))
    lease = Lease(storage, "mine", print)
    lease.hold()
    lease.release()
    good = json.loads(storage.read(LEASE))
    good["holders"] = [{"host": "far", "pid": 7, "start": 1, "boot": "b", "pidns": "p", "renewed_at": 1.0e9}]
    wrong = ["1", None, [], {}, True, -5, 0, 1.5, 1e300, float("nan"), 10**30, "x" * 3]
    checked = 0
    for path in [
        *(k for k in good if k not in ("expires", "expires_at")),
        *(f"holders.0.{k}" for k in good["holders"][0]),
    ]:
        for value in [*wrong, "missing"]:
            record = json.loads(json.dumps(good))
            *parents, key = path.split(".")
            where = record
            for part in parents:
                where = where[int(part)] if part.isdigit() else where[part]
            if value == "missing":
                del where[key]
            else:
                where[key] = value
            data = json.dumps(record).encode()
            storage.write_replace(LEASE, data)
            try:
                Lease(storage, "mine", print).acquire()
            except LeaseHeld:  # a record that reads: another run's, held
                pass
            except UserError as refused:
                field = re.sub(r"\.(\d+)", r"[\1]", path)  # as the line names it: holders[0].pid
                told = f"({field} is missing)" if value == "missing" else f"({field}: "
                assert f"LEASE.json is not a lease ftrain can read {told}" in str(refused), (path, value, refused)
                assert str(refused).endswith("): if no run uses this storage, delete that file"), refused
                assert storage.read(LEASE) == data
                checked += 1
            else:  # taken: only values that are what the field holds
                taken = Record.decode(storage.read(LEASE))
                assert taken.generation >= 1 and isinstance(taken.generation, int), (path, value)
                storage.write_replace(LEASE, json.dumps(good).encode())
    print(f"{checked} damaged lease records refused in one line")
    assert checked > 70


def test_an_unsupervised_run_holds_its_log_directory_and_one_refused_there_gives_the_lease_back(tmp_path):
    """Rank 0 of a run without a supervisor holds its log directory as a supervisor does: a run told to log where
    another logs (another run's storage, say) is refused with one line before it writes anything, and the lease of its
    own storage it had just taken goes back; once the directory is free, the run of its storage starts there at once,
    and a run on another storage is still refused: the directory holds the first one's records."""
    logs = tmp_path / "logs"

    def config_of(storage: str) -> Config:
        return load_config(SMOKE, [f"log_dir={logs}"], storage=str(tmp_path / storage))

    first = claim(config_of("first"), True, lambda outcome: outcome, print)
    try:
        with pytest.raises(UserError) as refused:
            claim(config_of("second"), True, lambda outcome: outcome, print)
        assert str(refused.value) == (
            f"log directory {logs} is in use by another run (ftrain train pid {os.getpid()} on "
            f"{socket.gethostname()}): stop that run, or give this one a log directory of its own with log_dir=DIR"
        )
        assert Record.decode(Storage.open(str(tmp_path / "second")).read(LEASE)).entries == ()  # given back
        assert sorted(path.name for path in logs.iterdir()) == ["run.lock", "storage.txt"]  # nothing of the second's
        with pytest.raises(UserError, match="in use by another run"), claim_log_dir(logs, None, "supervisor", "x"):
            pass  # the supervisor of a run on the same log directory is refused alike
    finally:
        first.release()
    claim(config_of("first"), True, lambda outcome: outcome, print).release()
    (logs / "metrics.csv").write_text("iteration\n")  # the first run's records
    with pytest.raises(UserError, match=f"^log directory {logs} holds the records of the run on {tmp_path / 'first'} "):
        claim(config_of("second"), True, lambda outcome: outcome, print)
    assert Record.decode(Storage.open(str(tmp_path / "second")).read(LEASE)).entries == ()  # given back
    (logs / "run.lock").unlink()
    (logs / "run.lock").mkdir()  # a lock that cannot be taken at all (not ours to write, a file system without locks)
    with pytest.raises(UserError, match=rf"^log directory {logs} cannot be held \({logs}/run.lock: Is a directory\)"):
        claim(config_of("third"), True, lambda outcome: outcome, print)
    assert Record.decode(Storage.open(str(tmp_path / "third")).read(LEASE)).entries == ()  # given back too
