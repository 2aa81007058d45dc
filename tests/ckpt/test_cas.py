"""Compare-and-swap on servers that decide the conditions themselves, each a real one on 127.0.0.1: S3 (moto), Google
Cloud Storage (fake-gcs-server, from PyPI) and Azure Blob storage (Azurite), where a create of an object that exists
and a write from a stale version are refused, and (on Azure) all but one of writers racing from one version. A
storage whose compare-and-swap is not atomic is refused before the lease (``ftrain/ckpt/cas.py``): an S3 server that
ignores If-Match and If-None-Match (here moto behind a real HTTP proxy that drops those headers, as some
S3-compatible servers do), and a protocol without conditional writes; ``storage.plain_writes=true`` accepts it. On a
local file system, a compare-and-swap that waits for the lock a stopped process holds says so, naming it, and goes on
once it is free."""

from __future__ import annotations

import base64
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import pytest

from ftrain.ckpt import cas
from ftrain.ckpt.lease import Lease, LeaseHeld, read_record
from ftrain.ckpt.storage import Storage
from ftrain.errors import StorageUnavailable, UserError

from helpers import (
    HOLD_LOCK,
    REPO,
    StoreProxy,
    azurite_connection,
    child_env,
    create_bucket,
    create_container,
    create_gcs_bucket,
    free_port,
    gcs_options,
    train_command,
    wait_for,
)

RACERS = 8


@pytest.fixture
def careless_s3(s3_server) -> Iterator[dict]:
    """An S3 endpoint that ignores conditional writes: moto behind a proxy that drops their headers."""
    proxy = StoreProxy(s3_server["endpoint_url"], ignored=("If-Match", "If-None-Match"))
    try:
        yield {**s3_server, "endpoint_url": proxy.endpoint_url}
    finally:
        proxy.close()


@pytest.fixture(params=["s3", *(pytest.param(name, marks=pytest.mark.slow) for name in ("gcs", "azure"))])
def server_storage(request) -> Storage:
    """An empty storage on a server that decides the conditions itself: moto's S3, fake-gcs-server's Google Cloud
    Storage, Azurite's Azure Blob storage."""
    if request.param == "s3":
        return s3_storage(request.getfixturevalue("s3_server"))
    if request.param == "gcs":
        return Storage.open(*gcs_url(request.getfixturevalue("gcs_server")))
    return Storage.open(*azure_url(request.getfixturevalue("azurite_server")))


def s3_storage(server: dict) -> Storage:
    options = {"endpoint_url": server["endpoint_url"], "key": server["key"], "secret": server["secret"]}
    return Storage.open(f"s3://{create_bucket(server)}/run", options)


def gcs_url(server: dict) -> tuple[str, dict]:
    """``(url, options)`` of a storage in a fresh bucket of ``server`` (``gcs_server``)."""
    return f"gs://{create_gcs_bucket(server)}/run", gcs_options(server)


def azure_url(server: dict) -> tuple[str, dict]:
    """``(url, options)`` of a storage in a fresh container of ``server`` (``azurite_server``)."""
    return f"abfs://{create_container(server)}/run", {"connection_string": server["connection_string"]}


def test_a_server_that_honours_conditions_passes_the_probe_which_leaves_nothing(server_storage):
    cas.require_atomic(server_storage)
    assert server_storage.url in cas._checked and server_storage.list_files("") == {}


def test_the_server_refuses_a_create_of_what_exists_and_a_write_from_a_stale_version(server_storage):
    storage = server_storage
    cas.write(storage, "OBJECT", b"first", None)
    with pytest.raises(cas.Conflict):
        cas.write(storage, "OBJECT", b"again", None)  # create: it exists
    data, version = cas.read(storage, "OBJECT")
    assert data == b"first"
    cas.write(storage, "OBJECT", b"second", version)
    with pytest.raises(cas.Conflict):
        cas.write(storage, "OBJECT", b"stale", version)
    data, current = cas.read(storage, "OBJECT")
    assert data == b"second" and current != version
    storage.delete("OBJECT")
    assert cas.read(storage, "OBJECT") is None
    with pytest.raises(cas.Conflict):
        cas.write(storage, "OBJECT", b"gone", current)  # its version is gone with it


def test_an_exclusive_create_such_as_a_manifests_is_refused_where_other_bytes_exist(server_storage):
    server_storage.write_exclusive("MANIFEST.json", b"first")
    server_storage.write_exclusive("MANIFEST.json", b"first")  # its own bytes: a retried create that had landed
    with pytest.raises(FileExistsError):
        server_storage.write_exclusive("MANIFEST.json", b"second")
    assert server_storage.read("MANIFEST.json") == b"first"
    written = server_storage.modified("")  # how old a step without a manifest is: retention's age floor reads it
    assert written is not None and abs(time.time() - written) < 300
    assert 0 <= cas.age(server_storage, "MANIFEST.json") < 300  # by the server's clock: what a lease expires by
    assert cas.age(server_storage, "NOTHING") is None


def test_of_writers_racing_from_one_version_exactly_one_wins(azurite_server):
    """Creates racing, then writes racing from the version the winner left: each time one write lands, and the
    object holds its bytes. On Azure only: moto checks If-Match, then writes, without a lock (of 16 writers racing
    from one version, two won 8 times in 30), where S3 and Azure decide each request atomically."""
    storage, version = Storage.open(*azure_url(azurite_server)), None
    for _ in ("creates", "writes"):
        won = race(storage, version)
        data, version = cas.read(storage, "OBJECT")
        assert len(won) == 1 and data == f"writer {won[0]}".encode(), won


def race(storage: Storage, version: str | None) -> list[int]:
    """``RACERS`` threads write ``OBJECT`` from ``version`` at the same instant; the numbers of those whose write
    landed."""
    start = threading.Barrier(RACERS)

    def write(n: int) -> bool:
        start.wait()
        try:
            cas.write(storage, "OBJECT", f"writer {n}".encode(), version)
        except cas.Conflict:
            return False
        return True

    with ThreadPoolExecutor(RACERS) as pool:
        return [n for n, landed in enumerate(pool.map(write, range(RACERS))) if landed]


@pytest.mark.parametrize("server", ["azurite_server", "gcs_server"])
def test_the_lease_on_azure_and_gcs_is_refused_to_another_run_while_held(request, server: str):
    url, options = (azure_url if server == "azurite_server" else gcs_url)(request.getfixturevalue(server))
    held = Lease(Storage.open(url, options), "run-a", print)
    held.hold()
    with pytest.raises(LeaseHeld, match=r"is held by another run \(run-a, pid"):
        Lease(Storage.open(url, options), "run-b", print).hold()  # a storage client of its own
    held.release()
    second = Lease(Storage.open(url, options), "run-b", print)
    second.hold()
    second.release()
    record = read_record(Storage.open(url, options))[0]
    assert (record.run_id, record.generation, record.entries) == ("run-b", 2, ())


def test_no_azure_failure_shows_the_account_key(azurite_server):
    """A wrong key (refused by the server: a UserError) and an endpoint that does not answer (StorageUnavailable,
    after the retries): neither message shows a key, the right one or the wrong one."""
    key, url = azurite_server["key"], f"abfs://{create_container(azurite_server)}/run"
    wrong = base64.b64encode(os.urandom(32)).decode()
    refused = {"connection_string": azurite_connection(azurite_server["port"], wrong)}
    with pytest.raises(UserError, match=r"access denied to abfs://.*AuthorizationFailure") as denied:
        cas.require_atomic(Storage.open(url, refused, retries=0))
    silent = {"connection_string": azurite_connection(free_port(), key)}
    with pytest.raises(StorageUnavailable, match=r"failed after 2 attempts: ServiceRequestError") as unavailable:
        cas.read(Storage.open(url, silent, retries=1, base_delay=0.01), "LEASE.json")
    for error in (denied, unavailable):
        assert key not in str(error.value) and wrong not in str(error.value), error.value


def test_an_s3_server_that_ignores_conditions_is_refused_and_the_probe_leaves_nothing(careless_s3):
    storage = s3_storage(careless_s3)
    with pytest.raises(UserError, match=r"ignores conditional writes \(If-None-Match: \* was not refused\)"):
        Lease(storage, "run-a", print).hold()
    assert storage.list_files("") == {}, "neither the probe's object nor a lease"
    lease = Lease(storage, "run-a", print, plain_writes=True)  # the user accepts the risk
    lease.hold()
    lease.release()
    assert "LEASE.json" in storage.list_files("")


def test_the_cli_refuses_it_in_one_line_and_plain_writes_accepts_it(careless_s3, tmp_path):
    bucket = create_bucket(careless_s3)
    options = [f"--storage-option={key}={careless_s3[key]}" for key in ("endpoint_url", "key", "secret")]
    command = [*train_command(f"s3://{bucket}/run", "iterations=1", f"log_dir={tmp_path / 'logs'}"), *options]
    refused = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
    assert "ignores conditional writes" in refused.stderr and "storage.plain_writes=true" in refused.stderr
    assert careless_s3["secret"] not in refused.stderr
    accepted = subprocess.run(
        [*command, "storage.plain_writes=true"], cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=300
    )
    assert accepted.returncode == 0, accepted.stderr


def test_a_protocol_without_conditional_writes_is_refused_unless_accepted(tmp_path):
    storage = Storage.open("http://127.0.0.1:9/run")  # fsspec's HTTP filesystem: no conditional writes
    with pytest.raises(UserError, match=r"offers no conditional writes that ftrain uses: .*\.plain_writes=true"):
        cas.require_atomic(storage)
    cas.require_atomic(storage, plain_writes=True)  # accepted: nothing is asked of it here
    cas.require_atomic(Storage.open(str(tmp_path / "run")))  # local: flock and an atomic rename
    cas.require_atomic(Storage.open("memory://run"))  # one process


def test_a_local_wait_for_the_lock_is_told_naming_its_stopped_holder_and_ends_when_it_is_continued(
    tmp_path, monkeypatch, caplog
):
    monkeypatch.setattr(cas, "LOCK_PATIENCE", 0.5)
    caplog.set_level(logging.WARNING, logger="ftrain.ckpt.cas")
    storage = Storage.open(str(tmp_path / "run"))
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, storage.url], env=child_env(), stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline() == b"held\n"
        writer = threading.Thread(target=cas.write, args=(storage, "LEASE.json", b"mine", None))
        writer.start()
        wait_for(lambda: caplog.records, "the wait told", timeout=60)  # then the holder goes on and lets go
        assert writer.is_alive() and not storage.exists("LEASE.json")  # it waits meanwhile
        os.kill(holder.pid, signal.SIGCONT)
        writer.join(timeout=60)
        assert not writer.is_alive()
    finally:
        os.kill(holder.pid, signal.SIGCONT)
    assert holder.wait(timeout=30) == 0 and storage.read("LEASE.json") == b"mine"
    told, got = (record.getMessage() for record in caplog.records)
    named = rf"LEASE\.json\.lock has been locked for \d+ s by process {holder.pid} \(.*, stopped\)"
    assert re.search(named, told), told
    assert re.search(r"LEASE\.json\.lock: got the lock after \d+ s; going on", got), got


def test_a_wait_for_the_lock_ends_when_the_process_is_told_to_stop_waiting(tmp_path, monkeypatch):
    storage = Storage.open(str(tmp_path / "run"))
    holder = subprocess.Popen([sys.executable, "-c", HOLD_LOCK, storage.url], env=child_env(), stdout=subprocess.PIPE)
    try:
        assert holder.stdout.readline() == b"held\n"
        stop = threading.Event()
        monkeypatch.setattr(cas, "_stop_waiting", stop.is_set)
        threading.Timer(0.5, stop.set).start()
        with pytest.raises(cas.LockWaitStopped):
            cas.write(storage, "LEASE.json", b"mine", None)
    finally:
        os.kill(holder.pid, signal.SIGCONT)
    assert holder.wait(timeout=30) == 0 and not storage.exists("LEASE.json")
