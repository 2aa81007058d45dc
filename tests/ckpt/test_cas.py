"""A storage whose compare-and-swap is not atomic is refused before the lease (``ftrain/ckpt/cas.py``): an S3 server
that ignores If-Match and If-None-Match (here moto behind a real HTTP proxy that drops those headers, as some
S3-compatible servers do), and a protocol without conditional writes; ``storage.plain_writes=true`` accepts it."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator

import pytest

from ftrain.ckpt import cas
from ftrain.ckpt.lease import Lease
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError

from helpers import REPO, S3Proxy, child_env, create_bucket, train_command


@pytest.fixture
def careless_s3(s3_server) -> Iterator[dict]:
    """An S3 endpoint that ignores conditional writes: moto behind a proxy that drops their headers."""
    proxy = S3Proxy(s3_server["endpoint_url"], ignored=("If-Match", "If-None-Match"))
    try:
        yield {**s3_server, "endpoint_url": proxy.endpoint_url}
    finally:
        proxy.close()


def s3_storage(server: dict) -> Storage:
    options = {"endpoint_url": server["endpoint_url"], "key": server["key"], "secret": server["secret"]}
    return Storage.open(f"s3://{create_bucket(server)}/run", options)


def test_an_s3_server_that_honours_conditions_passes_the_probe_which_leaves_nothing(s3_server):
    storage = s3_storage(s3_server)
    cas.require_atomic(storage)
    assert storage.url in cas._checked and storage.list_files("") == {}


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
