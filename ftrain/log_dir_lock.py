"""One run per log directory (on each node).

The log directory holds what is this run's alone on this machine: ``config.yaml``, ``metrics.csv``, ``events.jsonl``,
the heartbeats (which a supervisor clears for a new attempt and whose pids it kills), the spool (which prunes steps it
did not write) and the attempts' logs. Two runs sharing one would overwrite each other's records and kill each other's
workers, so the run's holder, its supervisor or else an unsupervised run's rank 0, holds an exclusive ``flock`` on
``<log_dir>/run[-node-N].lock`` while it runs (the kernel drops it with the process, however it ends), and a second
one is refused with one line. It is taken after the storage's lease: a second run on the same local storage (its log
directory too) hears of the lease, which names the run. Several nodes of one run on one host share the directory, one
lock each. Imports: errors.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
from collections.abc import Iterator
from pathlib import Path

from ftrain.errors import UserError


@contextlib.contextmanager
def claim_log_dir(log_dir: Path, node: int | None, holder: str) -> Iterator[None]:
    """Hold ``log_dir`` for this run (``node``: this node's number on several nodes, else None; ``holder``: what
    holds it, e.g. "supervisor", shown to a run refused) for the ``with`` block; UserError naming the holder and the
    way out if another run holds it."""
    log_dir.mkdir(parents=True, exist_ok=True)
    path = log_dir / f"run{'' if node is None else f'-node-{node}'}.lock"
    try:
        lock = path.open("a+")
    except OSError as error:
        raise _cannot_hold(log_dir, path, error) from None
    with lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
            lock.truncate(0)
            lock.write(f"{holder} pid {os.getpid()} on {socket.gethostname()}\n")  # for a run refused to read
            lock.flush()
        except BlockingIOError:
            lock.seek(0)
            other = lock.read().strip() or "another run"
            raise UserError(
                f"log directory {log_dir} is in use by another run ({other}): stop that run, or give this one a log "
                "directory of its own with log_dir=DIR"
            ) from None
        except OSError as error:  # no locks on that file system, a full disk
            raise _cannot_hold(log_dir, path, error) from None
        yield


def _cannot_hold(log_dir: Path, path: Path, error: OSError) -> UserError:
    """A lock file that is not ours to write, a file system without locks, a full disk."""
    return UserError(
        f"log directory {log_dir} cannot be held ({path}: {error.strerror or error}): give this run a log directory "
        "on a local file system you can write, with log_dir=DIR"
    )
