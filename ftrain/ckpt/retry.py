"""The retry policy of every storage request: what counts as transient, and how long to wait before the next try.

A transient failure (connection refused or reset, timeouts, DNS, 5xx, throttling, a hung mount) is an outage that
waiting fixes; anything else fails at once. Waits double from a base up to a cap (``Backoff``), with jitter from a
generator of this module's own, reseeded in every forked process, so that many ranks or nodes (warm workers are forks
of one pool) never knock at a recovering server in step. Two schedules: ``REQUEST``, between the few tries of one
request (``Storage``), and ``OUTAGE``, between the tries of a storage that is down until a deadline (a held save, the
supervisor's wait for a storage down at start), with a console line every ``WAIT_LINES`` seconds.
"""

from __future__ import annotations

import asyncio
import errno
import math
import os
import random
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

from botocore.exceptions import BotoCoreError, HTTPClientError
from botocore.exceptions import ConnectionError as BotoConnectionError

DEFAULT_RETRIES = 4
_JITTER = random.Random()
"""Jitter of the retry delays: a generator of its own, so that retrying never moves the random streams of training;
reseeded in every forked child (warm workers are forks of one pool: they would back off in step)."""
os.register_at_fork(after_in_child=_JITTER.seed)

_THROTTLING = {"SlowDown", "Throttling", "ThrottlingException", "RequestLimitExceeded", "TooManyRequestsException"}
_MOUNT_FAILURES = {errno.EIO, errno.ESTALE, errno.ENOTCONN, errno.EHOSTDOWN, errno.ENOLINK}


def is_transient(exc: BaseException) -> bool:
    """Worth retrying: the connection failed or timed out, the server was busy (5xx, 429, throttling; S3's or Azure's
    answer), or a mounted filesystem failed as a hung NFS or FUSE mount does (EIO, ESTALE, ENOTCONN): an outage,
    waited out like S3's."""
    if isinstance(exc, (ConnectionError, TimeoutError, asyncio.TimeoutError, BotoConnectionError, HTTPClientError)):
        return True
    if isinstance(exc, OSError) and exc.errno in _MOUNT_FAILURES:
        return True
    if isinstance(exc, loaded_errors(AZURE, "ServiceRequestError", "ServiceResponseError")):  # no answer, or late
        return True
    if isinstance(exc, loaded_errors(AIOHTTP, "ClientConnectionError")):  # gcsfs's session: no connection, or late
        return True
    if isinstance(exc, loaded_errors(AZURE, "HttpResponseError")):
        status = exc.status_code or 0
        return status >= 500 or status == 429
    if isinstance(exc, loaded_errors(REQUESTS, "ConnectionError", "Timeout")):  # gcsfs's word for a 502 too
        return True
    if isinstance(exc, loaded_errors(GCSFS, "HttpError")):  # Google's answer; a 401 of a token just expired, as gcsfs
        status = exc.code or 0
        return status >= 500 or status in (408, 429) or (status == 401 and "Invalid Credentials" in str(exc))
    response = getattr(exc.__cause__, "response", None) or getattr(exc, "response", None)
    if not isinstance(response, dict):
        return False
    status = response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0)
    return status >= 500 or status == 429 or response.get("Error", {}).get("Code") in _THROTTLING


def is_denied(exc: BaseException) -> bool:
    """The storage refused the credentials or their permissions (HTTP 401 or 403): bad input, never an outage.
    Azure's errors carry the status; gcsfs's ``HttpError`` its code, and gcsfs raises a 403 as a plain ``OSError``
    whose text starts with "Forbidden:" (S3's denials are ``PermissionError``, caught by their type)."""
    if getattr(exc, "status_code", None) in (401, 403):
        return True
    if isinstance(exc, loaded_errors(GCSFS, "HttpError")):
        return exc.code in (401, 403)
    return type(exc) is OSError and exc.errno is None and str(exc).startswith("Forbidden: ")


@dataclass(frozen=True)
class Backoff:
    """Doubling waits: ``first`` seconds before the first retry, at most ``longest``, each with +-25% jitter so that
    many ranks or nodes do not knock at a recovering server at the same instant."""

    first: float
    longest: float

    def delay(self, attempt: int) -> float:
        """Seconds before retry ``attempt + 1``."""
        return min(self.first * 2**attempt, self.longest) * _JITTER.uniform(0.75, 1.25)


REQUEST = Backoff(0.2, 5.0)
"""Between the tries of one storage request (``Storage``: ``checkpoint.retries`` of them, then it fails)."""
OUTAGE = Backoff(1.0, 5.0)
"""Between the tries of a storage that is down, until a deadline: a held save (``manager``), the supervisor's wait
(``supervise/outage.py``). Short: every second between the storage's return and the next try is lost to the whole
run, and a try of a storage that is down costs a request per file."""


WAIT_LINES = 30.0
"""Seconds between two console lines about a wait for the storage (the first and the end of a wait are always told):
where the tries come every few seconds, a line each would flood the log of a long outage."""


class WaitLines:
    """When the next line about a wait for the storage is due: the first at once, then every ``WAIT_LINES`` s."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._told = -math.inf

    def due(self, always: bool = False) -> bool:
        """Whether to print a line now (``always``: yes, and the next one is ``WAIT_LINES`` seconds from now)."""
        now = self._clock()
        if not always and now - self._told < WAIT_LINES:
            return False
        self._told = now
        return True


AZURE = "azure.core.exceptions"
AIOHTTP = "aiohttp.client_exceptions"
GCSFS = "gcsfs.retry"
REQUESTS = "requests.exceptions"
"""Modules of the exceptions of the stores' own clients (adlfs's azure-core; gcsfs's aiohttp session, its own errors
and those of requests it raises)."""


def client_errors() -> tuple[type[BaseException], ...]:
    """What a storage request may fail with: the OS's errors (local paths, mounts), botocore's (S3), and those of the
    clients of adlfs (Azure) and gcsfs (its aiohttp session, and its own) where they are loaded."""
    return (
        OSError,
        BotoCoreError,
        asyncio.TimeoutError,
        *loaded_errors(AZURE, "AzureError"),
        *loaded_errors(GCSFS, "HttpError"),
        *loaded_errors(AIOHTTP, "ClientError"),
    )


def loaded_errors(module: str, *names: str) -> tuple[type[Exception], ...]:
    """The exception classes ``names`` of ``module``, none where it is not loaded: only a process that loaded a store's
    client (adlfs, gcsfs) can meet its errors, and importing it would cost every other process a tenth of a second."""
    loaded = sys.modules.get(module)
    return tuple(getattr(loaded, name) for name in names) if loaded else ()
