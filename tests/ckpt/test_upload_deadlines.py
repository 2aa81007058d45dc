"""How long an upload may take, on Google Cloud Storage and Azure Blob storage (S3's: tests/supervise/test_outages.py),
through a real HTTP proxy in front of each store's emulator (fake-gcs-server, Azurite) that takes request bodies at
4 MB/s and stalls uploads on demand: a steady upload gets the time its size needs, whatever the read timeout; one the
server takes and never answers is given up (``ftrain.ckpt.stores``), as an outage that ``Storage`` retries."""

from __future__ import annotations

import os
import time

import pytest

from ftrain.ckpt.retry import is_transient
from ftrain.ckpt.storage import Storage
from ftrain.ckpt.stores import S3_TIMEOUTS, SLOWEST_UPLOAD

from helpers import StoreProxy, azurite_connection, create_container, create_gcs_bucket, gcs_options

pytestmark = pytest.mark.slow

READ_TIMEOUT = 4
"""Each store's read timeout here (``requests_timeout`` on GCS, ``read_timeout`` on Azure; 15 s by default): once the
proxy has the last 4 MB (loopback's buffers, 1 s at 4 MB/s), the emulator's answer comes within it on a busy machine."""


@pytest.fixture(params=["gcs", "azure"])
def slow_link(request) -> tuple[StoreProxy, Storage]:
    """A storage on the store's emulator through the proxy, which stalls the store's uploads (GCS's are POSTs)."""
    if request.param == "gcs":
        server = request.getfixturevalue("gcs_server")
        proxy = StoreProxy(server["endpoint_url"], stalls=("POST",), rate=4_000_000)
        options = {**gcs_options(server), "endpoint_url": proxy.endpoint_url, "requests_timeout": READ_TIMEOUT}
        url = f"gs://{create_gcs_bucket(server)}/run"
    else:
        server = request.getfixturevalue("azurite_server")
        proxy = StoreProxy(f"http://127.0.0.1:{server['port']}", stalls=("PUT",), rate=4_000_000)
        connection = azurite_connection(proxy.server.server_address[1], server["key"])
        options = {"connection_string": connection, "read_timeout": READ_TIMEOUT}
        url = f"abfs://{create_container(server)}/run"
    try:
        yield proxy, Storage.open(url, options)
    finally:
        proxy.stalling.clear()
        proxy.close()


@pytest.mark.waits  # a throttled link: a few percent of it on the CPU
def test_an_upload_on_a_slow_link_gets_the_time_its_size_needs(slow_link) -> None:
    """gcsfs gave each request its ``requests_timeout`` as a whole, so that a shard (one request up to 50 MiB) failed
    on any link slower than its size over that time (3.4 MB/s for 50 MiB at the default 15 s), retried until the save
    gave up. The read timeout is the wait for an answer: a stalled small upload is given up then."""
    proxy, storage = slow_link
    data = os.urandom(32 * 1024 * 1024)  # 8.4 s at 4 MB/s, twice the read timeout
    storage.write_replace("shard.pt", data)
    assert storage.read("shard.pt") == data

    proxy.stalling.set()
    started = time.monotonic()
    with pytest.raises(Exception) as given_up:
        storage.fs.pipe_file(f"{storage.root}/stalled.pt", os.urandom(100_000))  # in the socket's buffers at once
    assert time.monotonic() - started < READ_TIMEOUT + 3
    assert is_transient(given_up.value), repr(given_up.value)


@pytest.mark.waits
def test_an_upload_that_a_server_never_takes_is_given_up_when_its_size_had_time_enough(slow_link) -> None:
    """A body larger than the socket's buffers, on a server that takes none of it, never starts aiohttp's read
    timeout: it held the upload for as long as the server stayed so (on Azure, and on S3 before its deadline). The
    timeouts and the body's size at ``SLOWEST_UPLOAD`` give it up."""
    proxy, storage = slow_link
    data = os.urandom(5 * 1024 * 1024)
    deadline = S3_TIMEOUTS["connect_timeout"] + READ_TIMEOUT + len(data) / SLOWEST_UPLOAD
    proxy.stalling.set()
    started = time.monotonic()
    with pytest.raises(TimeoutError) as given_up:  # fsspec's, from ours
        storage.fs.pipe_file(f"{storage.root}/stalled.pt", data)
    assert deadline - 0.5 < time.monotonic() - started < deadline + 5
    assert str(given_up.value.__cause__) == f"no answer in {deadline:.0f} s"


def test_a_client_that_fsspec_hands_out_again_keeps_its_timeouts(gcs_server) -> None:
    """With ``skip_instance_cache=false`` fsspec gives a second open of the same storage the same client: its
    timeouts are set once (set again, a deadline was the read timeout plus a whole ``ClientTimeout``: a TypeError on
    every upload of 64 KiB or more)."""
    options = {**gcs_options(gcs_server), "skip_instance_cache": False}
    url = f"gs://{create_gcs_bucket(gcs_server)}/run"
    first, second = Storage.open(url, dict(options)), Storage.open(url, dict(options))
    assert first.fs is second.fs
    data = os.urandom(100_000)
    second.write_replace("shard.pt", data)
    assert first.read("shard.pt") == data
