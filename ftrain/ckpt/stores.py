"""The object stores ftrain knows by protocol (S3, Google Cloud Storage, Azure Blob storage), and what each needs when
a storage is opened: listings read afresh (another node may have written since), a silent server given up on within
seconds, and the client's own retries off, so that ``Storage``'s retry loop is the only one.

May import: fsspec, ``ftrain.redact``, the standard library; S3's client (aiobotocore) once a storage names S3.
"""

from __future__ import annotations

import asyncio
import functools
import io
import logging
import types
from collections.abc import Awaitable
from typing import TypeVar
from urllib.parse import unquote, urlsplit

import fsspec

from ftrain.redact import display_url

T = TypeVar("T")

S3_TIMEOUTS = {"connect_timeout": 5, "read_timeout": 15}
"""botocore's defaults are 60 s each (the Azure SDK's 300 s; Azure storages get the same as S3's): a paused server
would hold one request for minutes, longer than the ranks' collectives wait for each other. Large objects go up in
parts, each its own request."""
SLOWEST_UPLOAD = 256 * 1024
"""Bytes per second a request's body must at least go up at (S3, GCS): a request gets the connect and read timeouts
plus its body's size at this rate, whole, before it is given up (``_deadline_session``, ``_gcs_send_once``). Per
request: the parts of a large object that go up side by side (s3fs sends up to 10) each need it."""
SENT_AT_ONCE = 64 * 1024
"""A body this small goes into the socket's buffer at once, so that aiohttp's read timeout starts with the request,
unless it first waits for ``100 Continue``."""
S3_PROTOCOLS = frozenset({"s3", "s3a"})
"""s3fs's protocols. Its class is imported (by fsspec) only for a storage that names one: importing s3fs takes a
second, in every ``ftrain ckpt`` command and every worker of a run on a local directory."""
GCS_PROTOCOLS = frozenset({"gs", "gcs"})
"""gcsfs's protocols: Google Cloud Storage."""
AZURE_PROTOCOLS = frozenset({"abfs", "abfss", "az"})
"""adlfs's protocols: Azure Blob storage (and Data Lake Gen2, which is Blob storage underneath)."""


def prepare(protocol: str, url: str, options: dict) -> str:
    """The URL to open, after ``options`` (in place) got what ``protocol``'s store needs."""
    if protocol in S3_PROTOCOLS:
        return _s3_options(url, options)
    if protocol in GCS_PROTOCOLS:
        logging.getLogger("gcsfs").setLevel(logging.CRITICAL)  # its traceback per failed request: Storage says it once
        options.setdefault("skip_instance_cache", True)
        options.setdefault("requests_timeout", S3_TIMEOUTS["read_timeout"])
    if protocol in AZURE_PROTOCOLS:
        _azure_options(options)
    return url


def send_once(fs: fsspec.AbstractFileSystem, protocol: str) -> None:
    """Turn off the retries of ``fs``'s own client, so that ours (``Storage``) are the only ones and a storage that is
    down is told within seconds, whichever store it is; once per instance (fsspec reuses one for the same options,
    where ``skip_instance_cache`` is set false)."""
    if getattr(fs, "_ftrain_sends_once", False):
        return
    if protocol in S3_PROTOCOLS:
        fs.retries = 1  # s3fs's own retry loop: one attempt, ours does the retrying
    if protocol in GCS_PROTOCOLS:
        _gcs_send_once(fs)
    if protocol in AZURE_PROTOCOLS:
        _azure_send_once(fs)
    fs._ftrain_sends_once = True


def _gcs_send_once(fs: fsspec.AbstractFileSystem) -> None:
    """Send each request of this gcsfs instance once, and give it S3's timeouts: gcsfs wraps its one request method
    in a retry of its own (6 tries over half a minute, so that a storage down at start took a minute and a half to
    tell) and takes no option for it; this instance gets the method unwrapped. gcsfs gives each request
    ``requests_timeout`` as a whole, which cut short every shard (one request up to 50 MiB) on a link slower than its
    size over that time: it is the wait for an answer here, and a body gets on top of it its time at
    ``SLOWEST_UPLOAD``."""
    import aiohttp  # gcsfs's own client

    send = types.MethodType(type(fs)._request.__wrapped__, fs)
    read = fs.requests_timeout or S3_TIMEOUTS["read_timeout"]
    fs.requests_timeout = aiohttp.ClientTimeout(sock_connect=S3_TIMEOUTS["connect_timeout"], sock_read=read)

    async def within_deadline(method: str, path: str, *args, data=None, **kwargs):
        sending = send(method, path, *args, data=data, **kwargs)
        size = _bytes_in(data)
        connect = S3_TIMEOUTS["connect_timeout"]
        return await (sending if size < SENT_AT_ONCE else _by_deadline(sending, size, connect, read))

    fs._request = within_deadline


def _s3_options(url: str, options: dict) -> str:
    """Move ``key:secret@`` out of an S3 URL into ``options``; make s3fs list afresh and never retry on its own."""
    parts = urlsplit(url)
    if "@" in parts.netloc:
        options.setdefault("key", unquote(parts.username or ""))
        options.setdefault("secret", unquote(parts.password or ""))
        url = display_url(url)
    options.setdefault("use_listings_cache", False)
    options.setdefault("skip_instance_cache", True)
    config = {**S3_TIMEOUTS, **(options.get("config_kwargs") or {})}
    config.setdefault("retries", {"total_max_attempts": 1})
    config.setdefault("http_session_cls", _deadline_session())
    options["config_kwargs"] = config
    return url


@functools.cache
def _deadline_session() -> type:
    """aiobotocore's HTTP session with a deadline on each request as a whole. aiohttp's read timeout starts only once
    the request's body is sent, so a server that takes the connection and never answers (paused, or stalled on its
    disk) held a PUT for as long as it stayed so, waiting for ``100 Continue`` or for the socket to drain, and with it
    the saves and the training behind them; past its deadline the request ends as a read timeout does, which
    ``Storage`` retries and then waits out as an outage."""
    from aiobotocore.httpsession import AIOHTTPSession
    from botocore.exceptions import ReadTimeoutError

    class DeadlineSession(AIOHTTPSession):
        async def send(self, request):  # aiobotocore's own signature
            size = _body_size(request)
            if size < SENT_AT_ONCE and "Expect" not in request.headers:  # read timeouts cover it from the start
                return await super().send(request)  # (a CompleteMultipartUpload may answer slowly for minutes)
            try:
                timeouts = (self._timeout.sock_connect or 0, self._timeout.sock_read or 0)
                return await _by_deadline(super().send(request), size, *timeouts)
            except TimeoutError as late:  # aiohttp's own timeouts come out of ``send`` as botocore's errors: ours
                raise ReadTimeoutError(endpoint_url=request.url, error=str(late) or "no answer") from None

    return DeadlineSession


def _body_size(request: object) -> int:
    """Bytes of an S3 request's body: its ``Content-Length``, or over HTTPS, where botocore sends uploads as
    ``aws-chunked`` without one, the size it declares in ``X-Amz-Decoded-Content-Length``, else the body's own."""
    headers = request.headers
    declared = headers.get("Content-Length") or headers.get("X-Amz-Decoded-Content-Length")
    if declared:
        return int(declared)
    return _bytes_in(request.body)


async def _by_deadline(sending: Awaitable[T], size: int, connect_timeout: float, read_timeout: float) -> T:
    """``sending``, given up with a TimeoutError past the connect and read timeouts plus ``size`` bytes at
    ``SLOWEST_UPLOAD``: aiohttp's read timeout starts only once a request's body is in the socket's buffers, so that a
    server that takes the connection and never reads (paused, or stalled on its disk) held an upload, and the saves
    and training behind it, for as long as it stayed so. Its own timeouts come out as they are."""
    seconds = connect_timeout + read_timeout + size / SLOWEST_UPLOAD
    try:
        async with asyncio.timeout(seconds) as deadline:
            return await sending
    except TimeoutError:
        if deadline.expired():
            raise TimeoutError(f"no answer in {seconds:.0f} s") from None
        raise


def _bytes_in(body: object) -> int:
    """Bytes of a request's body (bytes, or a stream from where it stands), 0 for anything else."""
    if isinstance(body, (bytes, bytearray, memoryview)):
        return len(body)
    if hasattr(body, "seek") and hasattr(body, "tell"):
        here = body.tell()
        size = body.seek(0, io.SEEK_END) - here
        body.seek(here)
        return size
    return 0


def _azure_options(options: dict) -> None:
    """Make adlfs list afresh (another node may have written since), and give up on a silent server within seconds,
    as on S3."""
    options.setdefault("use_listings_cache", False)
    options.setdefault("connection_timeout", S3_TIMEOUTS["connect_timeout"])
    options.setdefault("read_timeout", S3_TIMEOUTS["read_timeout"])


def _azure_send_once(fs: fsspec.AbstractFileSystem) -> None:
    """Turn off the retries of adlfs's Azure client (3 per request, 15-24 s apart: a minute and a half before a
    request to a server that is down fails), so that ours are the only ones, as on S3. adlfs takes no option for it:
    this sets the counts of the retry policy its client's pipeline runs (azure-storage-blob's ``_config``). Its
    uploads get S3's deadline, in the transport that every client made from adlfs's sends through."""
    policy = fs.service_client._config.retry_policy
    for name in ("total_retries", "connect_retries", "read_retries", "status_retries"):
        setattr(policy, name, 0)
    transport = fs.service_client._pipeline._transport
    send = transport.send

    async def within_deadline(request: object, **config: object):
        sending = send(request, **config)
        size = int(request.headers.get("Content-Length") or 0) or _bytes_in(getattr(request, "data", None))
        connect = config.get("connection_timeout") or transport.connection_config.timeout
        read = config.get("read_timeout") or transport.connection_config.read_timeout
        return await (sending if size < SENT_AT_ONCE else _by_deadline(sending, size, connect, read))

    transport.send = within_deadline
