"""Compare-and-swap of one small object of a storage: read it with its version, write it only if that version is
still the current one (``Conflict`` if another process changed it since).

S3 and Azure Blob storage (``abfs://``, ``az://``): the version is the ETag; a write is one PUT with
``If-Match: <ETag>`` (``If-None-Match: *`` to create): the server decides, atomically. Google Cloud Storage
(``gs://``): the version is the object's generation; a write is one upload with ``ifGenerationMatch`` (0 to create).
On Azure the requests go through the blob client adlfs holds, as they go through s3fs's on S3 and gcsfs's session on
GCS, and are sent once each (the Azure SDK's own retries off), so that the retry loop is ``Storage``'s alone. Local:
the version is a digest of the bytes; the read-check-write runs under an exclusive ``flock`` of a side file
``<object>.lock`` (released by the kernel if the process dies; a long wait for it is told, naming its holder, and
ends early only by ``stop_waiting_when``), and the new object is put in place by an atomic rename of a fsynced
temporary file. Other protocols (``memory://``: one process): a plain check, then the write.

The lease, the fence and every manifest's exclusive create rest on this, so a run checks its storage before it
takes the lease (``require_atomic``): a server that ignores the conditions (some S3-compatible ones do) would turn
them into silent overwrites, and is found by a probe, once per process: a create of an object that exists and a
write with a wrong version, each of which must be refused. A storage of another protocol (``http://``...) gets no
conditional write here; both are refused in one line, unless ``storage.plain_writes=true`` accepts the risk.
"""

from __future__ import annotations

import contextlib
import datetime
import fcntl
import hashlib
import json
import logging
import os
import secrets
import time
from collections.abc import AsyncIterator, Callable, Iterator
from email.utils import parsedate_to_datetime
from typing import TYPE_CHECKING, Any

import fsspec.asyn

from ftrain import procfs
from ftrain.ckpt.storage import Storage
from ftrain.ckpt.stores import S3_TIMEOUTS
from ftrain.errors import StorageError, UserError
from ftrain.files import replace_file

if TYPE_CHECKING:
    from azure.storage.blob.aio import BlobClient

_CONFLICTS = ("PreconditionFailed", "ConditionalRequestConflict")
"""S3's answers to a condition that did not hold (412), or to a conditional write racing another one (409)."""
_AZURE_CONFLICTS = ("ConditionNotMet", "BlobAlreadyExists", "BlobNotFound")
"""Azure's answers to a condition that did not hold (412; 409 to a create of a blob that exists), and to one on a blob
that is gone (a missing container is no conflict: it fails as any storage error does)."""
_UNSUPPORTED = ("NotImplemented", "501", "ConditionHeadersNotSupported")
"""S3-compatible servers' (and Azure's) answers to a conditional header they do not implement."""
_AZURE_ONCE = {"connection_timeout": S3_TIMEOUTS["connect_timeout"], "read_timeout": S3_TIMEOUTS["read_timeout"]}
"""Each Azure request given up on within seconds, as on S3 (and sent once: ``Storage.open`` turns the client's retries
off): ``Storage._call`` does the retrying."""


PROBE = "CAS_PROBE"
"""The name of the probe's object (with a random suffix), deleted right after."""
RISK = (
    "two runs or nodes could overwrite each other's lease, fence and manifests; use a local or shared path, Google "
    "Cloud Storage, Azure Blob storage, or an S3 service that honours If-Match and If-None-Match (AWS S3, MinIO, "
    "Ceph), or pass "
    "storage.plain_writes=true to accept the risk"
)
LOCK_POLL = 0.02
"""Seconds between two tries of a local lock (a compare-and-swap holds it for milliseconds)."""
LOCK_PATIENCE = 10.0
"""Seconds a local lock is waited for before the wait is told, with who holds it."""


def _never() -> bool:
    return False


_stop_waiting: Callable[[], bool] = _never


class LockWaitStopped(BaseException):
    """A wait for a local lock ended by ``stop_waiting_when`` (a BaseException: no retry loop takes it for a storage
    error)."""


def stop_waiting_when(check: Callable[[], bool]) -> None:
    """End this process's waits for a local lock with ``LockWaitStopped`` once ``check()`` is true (a supervisor's stop
    signal before its run holds the storage: nothing is written yet, and nothing to save)."""
    global _stop_waiting
    _stop_waiting = check


log = logging.getLogger(__name__)
_checked: set[str] = set()
"""The storages this process found atomic."""


class Conflict(Exception):
    """The object changed since it was read (another process wrote it): read it again."""


def require_atomic(storage: Storage, plain_writes: bool = False) -> None:
    """UserError unless a compare-and-swap on ``storage`` is atomic (see the module doc); ``plain_writes``: accept
    one that is not."""
    if plain_writes or storage.is_local or storage.fs.protocol == "memory" or storage.url in _checked:
        return
    if not _server_decides(storage):
        raise UserError(f"storage {storage.url} offers no conditional writes that ftrain uses: {RISK}")
    name, written = f"{PROBE}-{secrets.token_hex(4)}", False
    try:
        write(storage, name, b"0", None)
        written = True
        other = "1" if storage.is_gcs else '"0"'  # a generation, or an ETag, that the object does not have
        for condition, version in (("If-None-Match: *", None), ("If-Match with another version", other)):
            try:
                write(storage, name, b"1", version)
            except Conflict:
                continue
            raise UserError(f"storage {storage.url} ignores conditional writes ({condition} was not refused): {RISK}")
    except StorageError as error:
        if not any(code in str(error) for code in _UNSUPPORTED):
            raise
        raise UserError(f"storage {storage.url} does not take conditional writes ({error}): {RISK}") from None
    finally:
        # not after a first write that failed (a storage that does not answer: the delete would wait out its retries
        # too); a probe object left behind, by a write whose answer was lost, harms nothing
        with contextlib.suppress(StorageError):
            if written:
                storage.delete(name)
    _checked.add(storage.url)


def read(storage: Storage, rel: str) -> tuple[bytes, str] | None:
    """The object's bytes and version, None if there is none."""
    if not _server_decides(storage):
        try:
            data = storage.read(rel)
        except FileNotFoundError:
            return None
        return data, hashlib.sha256(data).hexdigest()
    get = _s3_get if storage.is_s3 else _gcs_get if storage.is_gcs else _azure_get
    try:
        return storage._call("read", rel, fsspec.asyn.sync, storage.fs.loop, get, storage, rel)
    except FileNotFoundError:
        return None


def age(storage: Storage, rel: str) -> float | None:
    """Seconds since the object ``rel`` was last written, by the storage's own clock: on S3, GCS and Azure the server's
    ``Date`` against the object's ``Last-Modified`` (one HEAD request); on a file system the file's time against that
    of a file written now beside it (``<rel>.clock``), both set by the same clock, the file server's on NFS. What a
    lease's expiry is measured in, so that no host's clock is compared with another's. None if there is no such
    object, or the storage does not tell its time."""
    if not _server_decides(storage):
        written = storage.written_at(rel)
        if written is None:
            return None
        storage.write_replace(f"{rel}.clock", b"")
        now = storage.written_at(f"{rel}.clock")
        return None if now is None else now - written
    head = _s3_head if storage.is_s3 else _gcs_head if storage.is_gcs else _azure_head
    try:
        written, now = storage._call("read", rel, fsspec.asyn.sync, storage.fs.loop, head, storage, rel)
    except FileNotFoundError:
        return None
    return None if now is None else (now - written).total_seconds()


def write(storage: Storage, rel: str, data: bytes, version: str | None) -> None:
    """Put ``data`` if the object's version is still ``version`` (None: if there is no object); Conflict if not."""
    if storage.is_s3:
        bucket, key = _bucket_key(storage, rel)
        condition = {"IfMatch": version} if version else {"IfNoneMatch": "*"}
        _s3_conditional(storage, rel, "put_object", Bucket=bucket, Key=key, Body=data, **condition)
        return
    if storage.is_azure:
        metadata = {"is_directory": "false"}  # as adlfs marks its files: its isfile() reads the mark
        _azure_conditional(storage, rel, "upload_blob", data, overwrite=True, metadata=metadata, **_azure_if(version))
        return
    if storage.is_gcs:
        storage._call("write", rel, fsspec.asyn.sync, storage.fs.loop, _gcs_upload, storage, rel, data, version or "0")
        return
    with locked(storage, rel):
        current = read(storage, rel)
        if (current[1] if current else None) != version:
            raise Conflict
        if storage.is_local:
            storage._call("write", rel, replace_file, _local_path(storage, rel), data, durable=True)
        else:
            storage.write_replace(rel, data)


def _s3_conditional(storage: Storage, rel: str, operation: str, **kwargs) -> None:
    """One conditional S3 request, retried like any storage call while the failure is transient."""

    def call() -> None:
        try:
            storage.fs.call_s3(operation, **kwargs)
        except (FileExistsError, FileNotFoundError):  # s3fs's names for a failed If-None-Match, and a missing key
            raise Conflict from None
        except OSError as error:
            response = getattr(error.__cause__, "response", None) or {}
            if response.get("Error", {}).get("Code") in _CONFLICTS:
                raise Conflict from None
            raise

    storage._call(operation.partition("_")[0], rel, call)


def _server_decides(storage: Storage) -> bool:
    """Whether the server itself takes conditional writes (S3, GCS, Azure): no lock of ours, no read before a write."""
    return storage.is_s3 or storage.is_gcs or storage.is_azure


async def _s3_get(storage: Storage, rel: str) -> tuple[bytes, str]:
    """One GET: the bytes and the ETag of the same version."""
    bucket, key = _bucket_key(storage, rel)
    response = await storage.fs._call_s3("get_object", Bucket=bucket, Key=key)
    async with response["Body"] as body:
        return await body.read(), response["ETag"]


async def _s3_head(storage: Storage, rel: str) -> tuple[datetime.datetime, datetime.datetime | None]:
    """One HEAD: when the object was written, and the server's time of the answer."""
    bucket, key = _bucket_key(storage, rel)
    response = await storage.fs._call_s3("head_object", Bucket=bucket, Key=key)
    return response["LastModified"], _server_time(response["ResponseMetadata"]["HTTPHeaders"].get("date"))


async def _gcs_get(storage: Storage, rel: str) -> tuple[bytes, str]:
    """One GET of the object's data: the bytes and the generation of the same version."""
    headers, data = await storage.fs._call("GET", "b/{}/o/{}", *_bucket_key(storage, rel), alt="media")
    return data, headers["X-Goog-Generation"]


async def _gcs_head(storage: Storage, rel: str) -> tuple[datetime.datetime, datetime.datetime | None]:
    """One GET of the object's metadata: when it was written, and the server's time of the answer."""
    headers, body = await storage.fs._call("GET", "b/{}/o/{}", *_bucket_key(storage, rel))
    written = datetime.datetime.fromisoformat(json.loads(body)["updated"].replace("Z", "+00:00"))
    return written.replace(microsecond=0), _server_time(headers.get("Date"))  # (whole seconds, as the Date)


async def _gcs_upload(storage: Storage, rel: str, data: bytes, generation: str) -> None:
    """One multipart upload (gcsfs's own request for a small object) with ``ifGenerationMatch``; Conflict where the
    object's generation is another (gcsfs says FileExistsError for the 412)."""
    bucket, key = _bucket_key(storage, rel)
    boundary = f"ftrain-{secrets.token_hex(8)}"
    head = f"--{boundary}\r\nContent-Type: application/json; charset=UTF-8\r\n\r\n{json.dumps({'name': key})}\r\n"
    head += f"--{boundary}\r\nContent-Type: application/octet-stream\r\n\r\n"
    try:
        await storage.fs._call(
            "POST",
            f"{storage.fs._location}/upload/storage/v1/b/{bucket}/o",
            uploadType="multipart",
            ifGenerationMatch=generation,
            headers={"Content-Type": f'multipart/related; boundary="{boundary}"'},
            data=head.encode() + data + f"\r\n--{boundary}--".encode(),
            json_out=True,
        )
    except FileExistsError:
        raise Conflict from None


async def _azure_head(storage: Storage, rel: str) -> tuple[datetime.datetime, datetime.datetime | None]:
    """One HEAD: when the blob was written, and the server's time of the answer."""
    dates: list[str | None] = []
    async with _blob(storage, rel) as blob:
        properties = await blob.get_blob_properties(
            raw_response_hook=lambda answer: dates.append(answer.http_response.headers.get("Date")), **_AZURE_ONCE
        )
    return properties.last_modified, _server_time(dates[-1] if dates else None)


def _server_time(date: str | None) -> datetime.datetime | None:
    """An HTTP answer's ``Date`` header as a time; None where the server sent none (or one that does not parse)."""
    try:
        return parsedate_to_datetime(date) if date else None
    except (TypeError, ValueError):
        return None


async def _azure_get(storage: Storage, rel: str) -> tuple[bytes, str]:
    """One GET: the bytes and the ETag of the same version."""
    async with _blob(storage, rel) as blob:
        download = await blob.download_blob(**_AZURE_ONCE)
        return await download.readall(), download.properties.etag


def _azure_conditional(storage: Storage, rel: str, operation: str, *args: Any, **kwargs: Any) -> None:
    """One conditional request to the blob ``rel`` (the blob client's ``operation``), retried like any storage call
    while the failure is transient; Conflict where Azure refused its condition."""
    from azure.core.exceptions import HttpResponseError

    async def call() -> None:
        async with _blob_client(storage, rel) as blob:
            try:
                await getattr(blob, operation)(*args, **kwargs, **_AZURE_ONCE)
            except HttpResponseError as error:
                if error.error_code in _AZURE_CONFLICTS:
                    raise Conflict from None
                raise

    storage._call(operation.partition("_")[0], rel, fsspec.asyn.sync, storage.fs.loop, call)


def _azure_if(version: str | None) -> dict[str, Any]:
    """The Azure SDK's arguments for ``If-Match: version`` (``If-None-Match: *`` where ``version`` is None)."""
    from azure.core import MatchConditions

    if version is None:
        return {"match_condition": MatchConditions.IfMissing}
    return {"etag": version, "match_condition": MatchConditions.IfNotModified}


@contextlib.asynccontextmanager
async def _blob(storage: Storage, rel: str) -> AsyncIterator[BlobClient]:
    """The client of blob ``rel`` to read it with: one that is not there is FileNotFoundError, as s3fs says it."""
    from azure.core.exceptions import ResourceNotFoundError

    async with _blob_client(storage, rel) as client:
        try:
            yield client
        except ResourceNotFoundError:
            raise FileNotFoundError(rel) from None


def _blob_client(storage: Storage, rel: str) -> BlobClient:
    """The client of blob ``rel``, from the service client adlfs holds (its credentials and connection pool)."""
    container, blob = _bucket_key(storage, rel)
    return storage.fs.service_client.get_blob_client(container, blob)


@contextlib.contextmanager
def locked(storage: Storage, rel: str) -> Iterator[None]:
    """On a file system, an exclusive ``flock`` of ``<rel>.lock`` meanwhile (what every compare-and-swap of ``rel``
    takes); elsewhere nothing: the server decides each request alone."""
    if not storage.is_local:
        yield
        return
    fd = storage._call("lock", rel, _lock_file, _local_path(storage, rel) + ".lock")  # a failing mount: an outage
    try:
        yield
    finally:
        os.close(fd)


def _lock_file(path: str) -> int:
    """A descriptor of ``path`` (created, with its directory, where missing) holding an exclusive ``flock`` of it."""
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        _wait_for_lock(fd, path)
    except BaseException:
        os.close(fd)
        raise
    return fd


def _wait_for_lock(fd: int, path: str) -> None:
    """Take the lock, however long its holder keeps it: the holder is inside a compare-and-swap or a commit, which
    must end before another begins. Past ``LOCK_PATIENCE`` the wait is told in one line naming the holder (a process
    paused inside, by SIGSTOP or a frozen machine, keeps it until it goes on or ends), and its end in another."""
    began = time.monotonic()
    told = False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            pass
        if _stop_waiting():
            raise LockWaitStopped(path)
        waited = time.monotonic() - began
        if not told and waited > LOCK_PATIENCE:
            told = True
            holders = procfs.lock_holders(fd)
            named = ", ".join(map(procfs.describe, holders)) or "a process /proc/locks does not show (another host?)"
            log.warning(
                "%s has been locked for %.0f s by %s: every commit and lease change on this storage waits for it; "
                "a stopped holder keeps it until it is continued (kill -CONT) or ended",
                path,
                waited,
                named,
            )
        time.sleep(LOCK_POLL)
    if told:
        log.warning("%s: got the lock after %.0f s; going on", path, time.monotonic() - began)


def _local_path(storage: Storage, rel: str) -> str:
    return f"{storage.root}/{rel}"


def _bucket_key(storage: Storage, rel: str) -> tuple[str, str]:
    """The bucket (on Azure, the container) and the key of the object ``rel``."""
    bucket, _, prefix = storage.root.partition("/")
    return bucket, f"{prefix}/{rel}" if prefix else rel
