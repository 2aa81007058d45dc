"""The outage tooling itself, on a real moto server and real sockets: the proxy refuses and passes again, and a
SIGSTOPped server makes requests hang."""

from __future__ import annotations

import errno
import socket
import time

import botocore.config
import botocore.exceptions
import botocore.session
import pytest

from ftrain.ckpt.storage import Storage, StorageError

from helpers import S3_KEY, S3_REGION, S3_SECRET


def s3_client(endpoint_url: str, timeout: float = 5):
    """A plain botocore client without retries: one request, one outcome."""
    config = botocore.config.Config(connect_timeout=timeout, read_timeout=timeout, retries={"max_attempts": 1})
    return botocore.session.get_session().create_client(
        "s3",
        endpoint_url=endpoint_url,
        aws_access_key_id=S3_KEY,
        aws_secret_access_key=S3_SECRET,
        region_name=S3_REGION,
        config=config,
    )


def bucket_and_key(url: str, name: str) -> tuple[str, str]:
    bucket, _, prefix = url.removeprefix("s3://").partition("/")
    return bucket, f"{prefix}/{name}"


def test_refused_port_fails_requests_and_restore_serves_them_again(s3_outage):
    server = s3_outage.server
    client = s3_client(server.endpoint_url)
    bucket, key = bucket_and_key(s3_outage.url, "a")
    client.put_object(Bucket=bucket, Key=key, Body=b"before")
    storage = Storage.open(s3_outage.url, s3_outage.options, retries=0)  # s3fs (aiohttp) through the proxy

    server.refuse()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", server.proxy.port), timeout=2)
    with pytest.raises(botocore.exceptions.EndpointConnectionError):
        client.get_object(Bucket=bucket, Key=key)
    with pytest.raises(StorageError, match=r"(?i)connect"):
        storage.read("a")

    server.restore()
    assert client.get_object(Bucket=bucket, Key=key)["Body"].read() == b"before"
    storage.write_replace("b", b"after")
    assert storage.read("b") == b"after"


def test_refuse_resets_connections_in_flight(s3_outage):
    """A kept-alive connection through the proxy is cut by ``refuse()``: its next read sees a reset or EOF."""
    server = s3_outage.server
    sock = socket.create_connection(("127.0.0.1", server.proxy.port), timeout=5)
    bucket, _ = bucket_and_key(s3_outage.url, "")
    sock.sendall(f"HEAD /{bucket} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    assert sock.recv(4096).startswith(b"HTTP/1.1")
    server.refuse()
    try:
        assert sock.recv(4096) == b""
    except OSError as error:
        assert error.errno == errno.ECONNRESET
    sock.close()


def test_many_concurrent_connections_pass(s3_outage):
    """s3fs keeps a pool of connections per process: the proxy carries many at once."""
    server = s3_outage.server
    socks = [socket.create_connection(("127.0.0.1", server.proxy.port), timeout=10) for _ in range(64)]
    bucket, _ = bucket_and_key(s3_outage.url, "")
    for sock in socks:
        sock.sendall(f"HEAD /{bucket} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    assert all(sock.recv(4096).startswith(b"HTTP/1.1 200") for sock in socks)
    for sock in socks:
        sock.close()


@pytest.mark.waits
def test_hung_server_makes_requests_time_out_until_continued(s3_outage):
    server = s3_outage.server
    client = s3_client(server.endpoint_url, timeout=1)  # for the hung request only: a loaded server may take 1 s
    bucket, key = bucket_and_key(s3_outage.url, "a")
    s3_client(server.endpoint_url).put_object(Bucket=bucket, Key=key, Body=b"x")
    server.hang()
    start = time.monotonic()
    with pytest.raises(botocore.exceptions.ReadTimeoutError):
        client.get_object(Bucket=bucket, Key=key)
    assert time.monotonic() - start >= 0.9  # it hung, it did not fail fast
    server.unhang()
    assert s3_client(server.endpoint_url).get_object(Bucket=bucket, Key=key)["Body"].read() == b"x"
