"""Checkpoint storage: an fsspec URL (local path, ``file://``, ``s3://``, ``gs://``, ``abfs://``, ``memory://``...),
one-object operations.

Nothing is ever renamed (a rename on S3 is a copy + delete, not atomic): a commit is one object written with
exclusive create; a local file is written under a temporary name and linked to its own (a link fails if the name
exists), so it is complete whenever it is visible, as an S3 object is.

Transient errors (connection refused or reset, timeouts, DNS, 5xx, throttling) are retried here with bounded
exponential backoff and jitter; the layers below (s3fs, botocore) are told not to retry, and to give up on a silent
server within seconds, so that the bound is ours alone (on Azure, adlfs gets the same timeouts, and its client's own
retries are turned off). A storage that stays unreachable raises :class:`StorageUnavailable`: an infrastructure fault
that waiting fixes, never bad input (a missing bucket, denied access or a malformed URL are
:class:`~ftrain.errors.UserError`; a bucket deleted under a supervised run is waited for: :class:`NoBucket`).
Credentials never appear in a message, repr or log line: every text that leaves this module is scrubbed. A run's
storage is guarded (``guarded``): every write and delete runs inside the holder's check (``fence.py``).
"""

from __future__ import annotations

import contextlib
import copy
import datetime
import errno
import functools
import logging
import os
import posixpath
import re
import time
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import fsspec
from botocore.exceptions import NoCredentialsError
from fsspec.implementations.local import LocalFileSystem

from ftrain.ckpt import localfs, stores
from ftrain.ckpt.retry import DEFAULT_RETRIES, REQUEST, Backoff, client_errors, is_denied, is_transient
from ftrain.ckpt.stores import AZURE_PROTOCOLS, GCS_PROTOCOLS, S3_PROTOCOLS
from ftrain.config import blocking_file, local_path
from ftrain.errors import NO_SPACE, StorageError, StorageUnavailable, UserError, name_too_long_line, no_space_line
from ftrain.redact import Url, display_url, scrub, secret_values, url_secrets

log = logging.getLogger(__name__)

T = TypeVar("T")

_SECRET_ENV = (
    "AWS_ACCESS_KEY_ID",
    "AWS_SECRET_ACCESS_KEY",
    "AWS_SESSION_TOKEN",
    "AZURE_STORAGE_ACCOUNT_KEY",
    "AZURE_STORAGE_CONNECTION_STRING",
    "AZURE_STORAGE_SAS_TOKEN",
    "AZURE_STORAGE_CLIENT_SECRET",
    "AZURE_CLIENT_SECRET",
)
"""Credentials that s3fs and adlfs read from the environment."""
_PROTOCOL = re.compile(r"^[a-zA-Z][a-zA-Z0-9+.-]*$")
_MISTYPED = re.compile(
    rf"^({'|'.join(sorted(S3_PROTOCOLS | GCS_PROTOCOLS | AZURE_PROTOCOLS))})(?::/?|//)(?!/)", re.IGNORECASE
)
"""A local path that is a remote URL with a slash or the colon missing (``s3:/bucket``, ``s3//bucket``): fsspec would
make it a directory of the working one."""


class NoBucket(UserError):
    """The storage's S3 bucket does not exist: a wrong URL at a start, but a bucket deleted under a run that reached
    it (a supervisor's, ``gone``), which it waits for as for an outage."""

    def __init__(self, bucket: str, endpoint: str) -> None:
        super().__init__(f"S3 bucket {bucket!r} does not exist at {endpoint}: create it or fix the URL")
        self.gone = (
            f"S3 bucket {bucket!r} at {endpoint} no longer exists (deleted since the run reached it): create it again"
        )


class Storage:
    """A storage root; every path below it is relative (``checkpoints/step-000000120/MANIFEST.json``)."""

    def __init__(
        self, fs: fsspec.AbstractFileSystem, root: str, url: str, secrets: list[str], retries: int, base_delay: float
    ):
        self.fs = fs
        self.root = root.rstrip("/")
        self.url = url
        """The URL without credentials: safe to print."""
        self.retries = retries
        self.backoff = Backoff(base_delay, REQUEST.longest)
        self._secrets = secrets
        self.guard: Callable[[bool], contextlib.AbstractContextManager] | None = None
        """What every write and delete runs inside (``guarded``): the holder's check (``fence.Fence.holding``)."""

    @classmethod
    def open(
        cls,
        url: str,
        options: dict | None = None,
        retries: int = DEFAULT_RETRIES,
        base_delay: float = REQUEST.first,
        check_bucket: bool = True,
    ) -> Storage:
        """Open the storage at ``url`` with fsspec ``options``; on S3, ``check_bucket`` that it answers and exists.
        ``retries``: how often a transient error is retried, waiting ``base_delay * 2**n`` seconds (at most
        ``REQUEST.longest``) before retry ``n + 1``."""
        if not isinstance(url, str) or not url.strip():
            raise UserError("storage URL is empty: pass a local path or an fsspec URL such as s3://bucket/prefix")
        if retries < 0:
            raise UserError(f"checkpoint.retries={retries} must be 0 or more")
        url, options = Url(url).reveal(), dict(options or {})  # the one place the credentials are read
        secrets = secret_values(options) + url_secrets(url) + [os.environ.get(name, "") for name in _SECRET_ENV]
        protocol = url.split("://", 1)[0].lower() if "://" in url else "file"
        shown = display_url(url)
        if not _PROTOCOL.match(protocol):
            raise UserError(f"storage URL {shown!r} is malformed: use a local path or protocol://location")
        if protocol == "file" and (typo := _MISTYPED.match(shown)):
            raise UserError(
                f"storage URL {shown!r} looks like a mistyped {typo[1]}:// URL: write "
                f"{typo[1]}://{shown[typo.end() :]}, or ./{shown} for a local directory of that name"
            )
        try:
            fsspec.get_filesystem_class(protocol)
        except ValueError:
            raise UserError(
                f"storage URL {shown!r}: unknown protocol {protocol!r}; use a local path, file://, s3://, gs:// or abfs://"
            ) from None
        except ImportError as exc:
            raise UserError(f"storage URL {shown!r} needs a package that is not installed: {exc}") from None
        if protocol in ("file", "local"):  # named as the path it is (file:///a%41 is /aA), in every line
            url = shown = local_path(url)
        else:
            _check_key(shown)
            url = stores.prepare(protocol, url, options)
        try:
            fs, root = fsspec.core.url_to_fs(url, **options)
        except Exception as exc:
            raise UserError(f"cannot open storage {shown!r}: {scrub(exc, secrets)}") from None
        storage = cls(fs, root, shown, secrets, retries, base_delay)
        stores.send_once(storage.fs, protocol)
        if check_bucket:
            storage.check()
        return storage

    def guarded(self, guard: Callable[[bool], contextlib.AbstractContextManager] | None) -> Storage:
        """The same storage, every write and delete inside ``guard(commit)``: ``commit`` unless a file's data."""
        other = copy.copy(self)
        other.guard = guard
        return other

    def holding(self, commit: bool = True) -> contextlib.AbstractContextManager:
        """What a write runs inside: the guard's check (``guarded``), or nothing."""
        return self.guard(commit) if self.guard is not None else contextlib.nullcontext()

    def with_retries(self, retries: int) -> Storage:
        """The same storage, with transient errors retried ``retries`` times instead."""
        other = copy.copy(self)
        other.retries = retries
        return other

    def __repr__(self) -> str:
        return f"Storage({self.url!r})"

    @property
    def is_local(self) -> bool:
        return isinstance(self.fs, LocalFileSystem)

    @functools.cached_property
    def lists_late(self) -> bool:
        """Whether a listing may lack what another host wrote seconds ago: a network or FUSE file system (NFS
        caches lookups). Object stores list what they hold."""
        return self.is_local and localfs.shared(self._path(""))

    @property
    def is_s3(self) -> bool:
        return not S3_PROTOCOLS.isdisjoint(self._protocols)

    @property
    def is_gcs(self) -> bool:
        """Google Cloud Storage through gcsfs, whose session and ``_call`` ``cas`` uses."""
        return not GCS_PROTOCOLS.isdisjoint(self._protocols)

    @property
    def is_azure(self) -> bool:
        """Azure Blob storage through adlfs, whose ``fs.service_client`` (azure.storage.blob.aio) ``cas`` uses."""
        return not AZURE_PROTOCOLS.isdisjoint(self._protocols)

    @property
    def _protocols(self) -> tuple[str, ...]:
        return (self.fs.protocol,) if isinstance(self.fs.protocol, str) else tuple(self.fs.protocol)

    def write_exclusive(self, rel: str, data: bytes, commit: bool = False) -> None:
        """Create ``rel`` holding ``data``; FileExistsError if it exists with other content. ``commit``: this object
        commits something (a manifest), see ``guarded``.

        Local: a temporary file linked to its name (complete when visible), fsynced; S3: one PUT with
        ``If-None-Match: *``; memory and other protocols: fsspec's ``mode="create"`` (an exists check, then a write:
        fine for one process). An object that already holds
        exactly ``data`` counts as written: a retried PUT (ours or the HTTP client's) whose first attempt landed
        finds its own bytes.
        """
        path = self._path(rel)

        def create() -> None:
            try:
                if self.is_local:
                    localfs.write(path, data, exclusive=True)
                else:
                    self.fs.pipe_file(path, data, mode="create")
            except FileExistsError:
                if self.fs.cat_file(path) != data:
                    raise

        with self.holding(commit):
            self._call("create", rel, create)

    def write_replace(self, rel: str, data: bytes) -> None:
        """Create or overwrite ``rel`` (not atomic: for markers and other objects that are not a commit)."""
        path = self._path(rel)
        with self.holding():
            if self.is_local:
                self._call("write", rel, localfs.write, path, data, exclusive=False)
            else:
                self._call("write", rel, self.fs.pipe_file, path, data)

    def read(self, rel: str) -> bytes:
        return self._call("read", rel, self.fs.cat_file, self._path(rel))

    def exists(self, rel: str) -> bool:
        return self._call("check", rel, self.fs.exists, self._path(rel))

    def forget_listing(self, rel: str) -> None:
        """Drop what a listings cache holds of directory ``rel`` (fsspec's, where storage options turn it on): the
        next look below it asks the storage itself."""
        self.fs.invalidate_cache(self._path(rel))

    def size(self, rel: str) -> int:
        return self._call("stat", rel, self.fs.size, self._path(rel))

    def list_dirs(self, rel: str) -> list[str]:
        """Sorted names of the directories directly under ``rel`` (none if ``rel`` does not exist)."""
        return sorted(name for name, entry in self._list(rel).items() if entry["type"] == "directory")

    def list_files(self, rel: str) -> dict[str, int]:
        """Name -> size of the files directly under ``rel`` (one listing, no per-file requests)."""
        return {name: int(entry["size"]) for name, entry in self._list(rel).items() if entry["type"] == "file"}

    def modified(self, rel: str) -> float | None:
        """When the newest file directly under ``rel`` was written (epoch seconds); None if there is none, or the
        storage does not say. How old an abandoned save is tells a dead one from one in flight."""
        times = [_modified(entry) for entry in self._list(rel).values() if entry["type"] == "file"]
        return max((time for time in times if time is not None), default=None)

    def written_at(self, rel: str) -> float | None:
        """When the object ``rel`` was last written (epoch seconds, the storage's clock); None if there is none, or
        the storage does not say."""
        try:
            return _modified(self._call("info", rel, self.fs.info, self._path(rel)))
        except FileNotFoundError:
            return None

    def delete(self, rel: str) -> None:
        """Delete one object if it exists."""
        with self.holding(), contextlib.suppress(FileNotFoundError):
            self._call("delete", rel, self.fs.rm_file, self._path(rel))

    def delete_files(self, rel: str, names: Iterable[str]) -> bool:
        """Delete the files ``names`` directly under ``rel``, absent ones included, without listing ``rel``: locally
        one by one, then the directory if that leaves it empty; on S3 in one request (other objects under ``rel``
        stay). False if the directory is not gone: something else is left in a local one, or the storage has
        directories of its own (delete the tree then)."""
        paths = [self._path(f"{rel}/{name}") for name in names]
        if not (self.is_local or self.is_s3):
            return False
        with self.holding():
            if self.is_local:
                return self._call("delete", rel, localfs.delete_files, self._path(rel), paths)
            self._call("delete", rel, self.fs.rm, paths)  # S3: no directories, and a batch delete takes absent keys
            return True

    def delete_tree(self, rel: str) -> None:
        """Delete ``rel`` and everything below it, if it exists."""
        with self.holding(), contextlib.suppress(FileNotFoundError):
            if self.is_local:  # fsspec would walk the tree first, then delete entry by entry
                self._call("delete", rel, localfs.delete, self._path(rel))
            else:
                self._call("delete", rel, self.fs.rm, self._path(rel), recursive=True)

    def where(self, rel: str = "") -> str:
        """The printable URL of ``rel``."""
        return f"{self.url.rstrip('/')}/{rel}" if rel else self.url

    def _path(self, rel: str) -> str:
        return f"{self.root}/{rel.strip('/')}" if rel else self.root

    def _list(self, rel: str) -> dict[str, dict]:
        try:
            entries = self._call("list", rel, self.fs.ls, self._path(rel), detail=True)
        except FileNotFoundError:
            return {}
        prefix = self._path(rel).rstrip("/") + "/"
        return {
            e["name"].rstrip("/").rpartition("/")[2]: e for e in entries if e["name"].rstrip("/").startswith(prefix)
        }

    def _call(self, what: str, rel: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        """``fn(*args, **kwargs)`` with retries; failures become StorageError or UserError with scrubbed text."""
        try:
            return self._retry(what, rel, fn, *args, **kwargs)
        except (FileNotFoundError, NotADirectoryError, FileExistsError) as exc:
            if what in ("create", "write") and (blocking := self._file_in_the_way(rel)) is not None:
                raise UserError(
                    f"cannot {what} {self.where(rel)}: {blocking} is a file where ftrain needs a directory: move it "
                    "out of the storage"
                ) from None
            if isinstance(exc, FileExistsError):
                raise FileExistsError(errno.EEXIST, "already exists", self.where(rel)) from None
            if what in ("create", "write") and (missing := self._missing_bucket()) is not None:
                raise FileNotFoundError(errno.ENOENT, missing.gone, self.where(rel)) from None
            # a path below a plain file does not exist either
            raise FileNotFoundError(errno.ENOENT, "does not exist", self.where(rel)) from None
        except IsADirectoryError:  # a directory where a file belongs: the caller tells what that file was
            raise IsADirectoryError(errno.EISDIR, "is a directory", self.where(rel)) from None
        except (PermissionError, NoCredentialsError) as exc:
            raise self._access_error(exc) from None
        except client_errors() as exc:
            if is_denied(exc):
                raise self._access_error(exc) from None
            if isinstance(exc, OSError) and exc.errno == errno.EROFS:  # as a denied write: no waiting fixes it
                raise UserError(
                    f"{what} {self.where(rel)} failed: read-only file system: pass a storage you can write to"
                ) from None
            if isinstance(exc, OSError) and exc.errno == errno.ENAMETOOLONG:
                raise UserError(name_too_long_line(OSError(exc.errno, exc.strerror, self.where(rel)))) from None
            if isinstance(exc, OSError) and exc.errno in NO_SPACE:  # waited for, as an outage: freeing space fixes it
                raise StorageUnavailable(no_space_line(OSError(exc.errno, exc.strerror, self.where(rel)))) from None
            if is_transient(exc):
                raise StorageUnavailable(
                    f"{what} {self.where(rel)} failed after {self.retries + 1} attempts: {self._scrub(exc)}"
                ) from None
            raise StorageError(f"{what} {self.where(rel)} failed: {self._scrub(exc)}") from None

    def _file_in_the_way(self, rel: str) -> str | None:
        """On a local storage, the file that stands where a directory above ``rel`` belongs (a stray file named as a
        step), which no waiting removes; None elsewhere."""
        return blocking_file(os.path.dirname(self._path(rel))) if self.is_local else None

    def _retry(self, what: str, rel: str, fn: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        attempt = 0
        while True:
            try:
                return fn(*args, **kwargs)
            except Exception as exc:
                if attempt == self.retries or not is_transient(exc):
                    raise
                delay = self.backoff.delay(attempt)
                attempt += 1
                where, reason = self.where(rel), self._scrub(exc)
                if attempt == 1:  # one line per failing request: the later retries say the same
                    more = f", then up to {self.retries - 1} more" if self.retries > 1 else ""
                    log.warning("%s %s: %s; retry 1/%d in %.2fs%s", what, where, reason, self.retries, delay, more)
                else:
                    log.debug("%s %s: %s; retry %d/%d in %.2fs", what, where, reason, attempt, self.retries, delay)
                time.sleep(delay)

    def check(self) -> None:
        """On S3, that the bucket answers and exists."""
        if not self.is_s3:
            return
        bucket = self.root.split("/", 1)[0]
        if not bucket:
            raise UserError(f"storage URL {self.url!r} names no bucket: use s3://bucket/prefix")
        try:
            self._retry("check", "", self.fs.call_s3, "head_bucket", Bucket=bucket)
        except FileNotFoundError:
            raise NoBucket(bucket, self._endpoint()) from None
        except (PermissionError, NoCredentialsError) as exc:
            raise self._access_error(exc) from None
        except Exception as exc:
            if is_transient(exc):
                raise StorageUnavailable(
                    f"cannot reach the S3 endpoint {self._endpoint()} for {self.url} after {self.retries + 1} "
                    f"attempts ({self._scrub(exc)}): is the server up, and AWS_ENDPOINT_URL or "
                    "storage.options.endpoint_url right?"
                ) from None
            raise UserError(f"cannot open storage {self.url}: {self._scrub(exc)}") from None

    def _missing_bucket(self) -> NoBucket | None:
        """On S3, NoBucket where a write found no place to go because the bucket is gone; None otherwise."""
        try:
            self.with_retries(0).check()
        except NoBucket as missing:
            return missing
        except (StorageError, UserError):
            pass
        return None

    def _endpoint(self) -> str:
        return display_url(self.fs.s3.meta.endpoint_url)

    def _access_error(self, exc: Exception) -> UserError:
        if isinstance(exc, NoCredentialsError):
            return UserError(
                f"no credentials for {self.url} (endpoint {self._endpoint()}): set AWS_ACCESS_KEY_ID and "
                "AWS_SECRET_ACCESS_KEY, or the storage options key and secret (--storage-option key=... "
                "--storage-option secret=..., storage.options in a config)"
            )
        return UserError(f"access denied to {self.url} ({self._scrub(exc)}): check the credentials and permissions")

    def _scrub(self, exc: BaseException) -> str:
        return scrub(exc, self._secrets)


def _check_key(shown: str) -> None:
    """UserError for a remote URL whose path has an empty, ``.`` or ``..`` part (``s3://bucket//run``): object keys
    keep them as written, so the storage would be other keys than the same place spelt plainly (another storage
    beside the one it names), and s3fs reads some of them back by another key than it wrote."""
    protocol, _, rest = shown.partition("://")
    bucket, _, key = rest.partition("/")
    parts = key.rstrip("/").split("/") if key.rstrip("/") else []
    if any(part in ("", ".", "..") for part in parts):
        plain = "/" + posixpath.normpath("/" + key).strip("/")  # POSIX keeps a leading // as it is
        raise UserError(
            f"storage URL {shown!r} has an empty, . or .. part in its path, which object stores keep as written: "
            f"write {protocol}://{bucket}{plain.rstrip('/')}"
        )


def _modified(entry: dict) -> float | None:
    """An fsspec listing entry's modification time: ``mtime`` locally, ``LastModified`` on S3, ``last_modified`` on
    Azure, ``created`` in memory."""
    value = next((entry[key] for key in ("mtime", "LastModified", "last_modified", "created") if key in entry), None)
    if isinstance(value, datetime.datetime):
        return value.timestamp()
    return float(value) if isinstance(value, (int, float)) else None
