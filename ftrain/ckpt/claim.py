"""Who holds a run's storage lease (``lease.py``) and its log directory (``ftrain.log_dir_lock``): ``ftrain
supervise`` for its workers, else rank 0 of the world (``claim``), which every rank calls at the start. Rank 0 draws
the run's id (``identity.run_id``), takes the lease, then the log directory (a run refused either keeps neither);
every other rank receives the identity it holds, so that every rank's writes are checked against it
(``fence.Fence``). Torch-free."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path

from ftrain.ckpt.lease import Lease, LeaseHeld, ttl_from_env
from ftrain.ckpt.steps import check_not_a_checkpoints_directory
from ftrain.ckpt.storage import NoBucket, Storage, StorageError, StorageUnavailable
from ftrain.config import Config, storage_key
from ftrain.errors import UserError
from ftrain.heartbeat import TOKEN_ENV
from ftrain.identity import Identity, restore_environ, run_id, saved_environ
from ftrain.log_dir_lock import claim_log_dir

_AGREED = {kind.__name__: kind for kind in (LeaseHeld, UserError, StorageUnavailable, StorageError)}
"""What rank 0's claim may end in, as the other ranks raise it too."""


def storage_lease(
    config: Config,
    log: Callable[[str], None],
    secret: bytes | None = None,
    endpoint: tuple[str, int] | None = None,
    retries: int | None = None,
    shared: bool = False,
    follows: bool = False,
) -> Lease:
    """The lease of ``config``'s storage for this run (``identity.run_id`` of ``secret`` and ``endpoint``), not taken
    yet. ``retries``: of the storage's requests (default: ``checkpoint.retries``); ``shared``, ``follows``: see
    ``Lease``."""
    retries = config.checkpoint.retries if retries is None else retries
    storage = Storage.open(config.storage.url, config.storage.options, retries=retries)
    check_not_a_checkpoints_directory(storage)
    return Lease(storage, run_id(secret, endpoint), log, ttl_from_env(), config.storage.plain_writes, shared, follows)


class Claim:
    """What ``claim`` leaves a rank: the lease and the log directory where this rank holds them, and the identity it
    gave this process."""

    def __init__(self, lease: Lease | None, held: contextlib.ExitStack, environ: dict[str, str | None]) -> None:
        self.lease = lease
        self._held = held
        """Releases what this rank holds, the log directory first, then the lease."""
        self._environ = environ

    @property
    def lost(self) -> str | None:
        """Why the storage is lost to another run, once the lease's renewal found it (rank 0 of an unsupervised run)."""
        return self.lease.lost if self.lease is not None else None

    def release(self) -> None:
        """Release the log directory and the lease (rank 0), and leave the environment as it was before ``claim``."""
        self._held.close()
        restore_environ(self._environ)


def claim(
    config: Config, is_main: bool, agree: Callable[[list | None], list | None], log: Callable[[str], None]
) -> Claim:
    """Every rank of a world calls this at the start. Rank 0 (``is_main``) holds the lease for the run, then its log
    directory (``ftrain.log_dir_lock``), or, started by ``ftrain supervise`` (which holds both), checks that no other
    run holds the lease; ``agree`` (a broadcast from rank 0) tells every rank how that went, so that every rank raises
    alike (LeaseHeld or UserError if refused) and none waits for a rank 0 that failed, and hands every rank the
    identity rank 0 holds (``Identity.env``)."""
    lease, outcome, failure = None, None, None
    held = contextlib.ExitStack()
    environ = saved_environ()
    if is_main:
        try:
            if os.environ.get(TOKEN_ENV):
                _check_for_supervisor(config, log)
            else:
                lease = storage_lease(config, log)
                taken = lease.hold()
                held.callback(lease.release)  # at the run's end, or at once if what follows fails
                if taken:
                    log(taken)
                held.enter_context(
                    claim_log_dir(Path(config.log_dir), None, "ftrain train", storage_key(config.storage.url))
                )
            identity = Identity.from_env()
            outcome = [None, identity.env() if identity is not None else {}]
        except Exception as error:
            held.close()  # the log directory and the lease, where taken: a refused run keeps nothing
            lease, failure = None, error
            outcome = [type(error).__name__ if type(error).__name__ in _AGREED else "StorageError", str(error)]
    outcome = agree(outcome)
    if failure is not None:
        raise failure
    if outcome[0] is not None:
        raise _AGREED[outcome[0]](outcome[1])
    os.environ.update(outcome[1])
    return Claim(lease, held, environ)


def _check_for_supervisor(config: Config, log: Callable[[str], None]) -> None:
    """A supervised worker's check that no other run holds the storage, in one try. The supervisor holds the lease:
    a storage that does not answer now is not checked (the run may go on from its spool, see ``ftrain.ckpt.spool``),
    nor a bucket deleted since the supervisor took the lease in it."""
    try:
        storage_lease(config, log, retries=0).check()
    except (StorageUnavailable, NoBucket) as error:
        why = error.gone if isinstance(error, NoBucket) else f"the storage does not answer: {error}"
        log(f"the lease was not checked ({why}); the supervisor holds it")
