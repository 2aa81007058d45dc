"""A run on Google Cloud Storage (``gs://``), on fake-gcs-server's real GCS JSON API from PyPI: its lease, fence and
manifests rest on ``ifGenerationMatch`` (tests/ckpt/test_cas.py), and a supervised run commits, verifies and resumes
there, and trains what a run on a local directory trains."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import pytest

from ftrain.ckpt.storage import Storage
from ftrain.ckpt.stores import S3_TIMEOUTS, SLOWEST_UPLOAD

from helpers import REPO, StoreProxy, child_env, create_gcs_bucket, gcs_options, run_train

pytestmark = pytest.mark.slow


def test_a_run_on_gcs_commits_verifies_resumes_and_trains_what_a_local_one_does(gcs_server, tmp_path, reference_state):
    url, options = f"gs://{create_gcs_bucket(gcs_server)}/run", gcs_options(gcs_server)
    flags = [f"--storage-option={key}={value}" for key, value in options.items()]
    run_train(url, "iterations=4", f"log_dir={tmp_path / 'logs'}", *flags, ranks=2, supervised=True)
    resumed = run_train(url, "iterations=8", f"log_dir={tmp_path / 'logs'}", *flags, ranks=2, supervised=True)
    assert "resumed from step 4" in resumed.stdout, resumed.stdout[-2000:]
    verify = subprocess.run(
        [sys.executable, "-m", "ftrain", "ckpt", "verify", url, *flags],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert verify.returncode == 0, verify.stderr[-3000:]
    storage = Storage.open(url, options)
    newest = max(storage.list_dirs("checkpoints"))
    manifest = json.loads(storage.read(f"checkpoints/{newest}/MANIFEST.json"))
    assert manifest["step"] == 8 and manifest["state_sha256"] == reference_state(8)


@pytest.fixture
def slow_link(gcs_server):
    """A storage on ``gcs_server`` through a proxy that takes request bodies at 4 MB/s and stalls POSTs (GCS's
    uploads) on demand, with ``requests_timeout=2``."""
    proxy = StoreProxy(gcs_server["endpoint_url"], stalls=("POST",), rate=4_000_000)
    options = {**gcs_options(gcs_server), "endpoint_url": proxy.endpoint_url, "requests_timeout": 2}
    try:
        yield proxy, Storage.open(f"gs://{create_gcs_bucket(gcs_server)}/run", options)
    finally:
        proxy.stalling.clear()
        proxy.close()


def test_an_upload_on_a_slow_link_gets_the_time_its_size_needs(slow_link) -> None:
    """gcsfs gives each request ``requests_timeout`` seconds as a whole, so that a shard (one request up to 50 MiB)
    failed on any link slower than its size over that time, 3.4 MB/s for 50 MiB at the default 15 s, and was retried
    until the save gave up. As on S3, the timeout is now the wait for an answer (a stalled small upload is given up
    by then), and an upload gets on top of it the time its size needs at ``SLOWEST_UPLOAD``."""
    proxy, storage = slow_link
    data = os.urandom(16 * 1024 * 1024)  # 4.2 s at 4 MB/s, the last 4 MB of it (loopback's buffers) in 1 s
    storage.write_replace("shard.pt", data)
    assert storage.read("shard.pt") == data

    proxy.stalling.set()
    started = time.monotonic()
    with pytest.raises(TimeoutError):
        storage.fs.pipe_file(f"{storage.root}/stalled.pt", os.urandom(100_000))  # in the socket's buffers at once
    assert time.monotonic() - started < 2 + 3


@pytest.mark.waits
def test_an_upload_that_a_server_never_takes_is_given_up_when_its_size_had_time_enough(slow_link) -> None:
    """A body larger than the socket's buffers, on a server that takes none of it, never starts aiohttp's read
    timeout: the upload's deadline (the timeouts and its size at ``SLOWEST_UPLOAD``) gives it up."""
    proxy, storage = slow_link
    data = os.urandom(5 * 1024 * 1024)
    deadline = S3_TIMEOUTS["connect_timeout"] + 2 + len(data) / SLOWEST_UPLOAD
    proxy.stalling.set()
    started = time.monotonic()
    with pytest.raises(TimeoutError) as given_up:  # fsspec's, from ours
        storage.fs.pipe_file(f"{storage.root}/stalled.pt", data)
    assert deadline - 0.5 < time.monotonic() - started < deadline + 5
    assert str(given_up.value.__cause__) == f"no answer in {deadline:.0f} s"
