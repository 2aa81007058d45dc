"""One run per log directory (on each node).

The log directory holds what is this run's alone on this machine: ``config.yaml``, ``metrics.csv``, ``events.jsonl``,
the heartbeats (which a supervisor clears for a new attempt and whose pids it kills), the spool (which prunes steps it
did not write) and the attempts' logs. Two runs sharing one would overwrite each other's records and kill each other's
workers, so the run's holder, its supervisor or else an unsupervised run's rank 0, holds an exclusive ``flock`` on
``<log_dir>/run.lock`` while it runs (the kernel drops it with the process, however it ends), and a second one is
refused with one line. It is taken after the storage's lease: a second run on the same local storage (its log
directory too) hears of the lease, which names the run. Several nodes of one run on one host share the directory: each
holds ``run-node-N.lock`` alone and ``run.lock`` shared, so a run on one node and a run on several exclude each other.
A log directory also belongs to one storage, which ``storage.txt`` names: once it holds that storage's records, a run
on another storage, even after the first has ended, is refused rather than let rewrite them.
Imports: errors, files.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import socket
from collections.abc import Iterable, Iterator
from pathlib import Path

from ftrain.errors import UserError
from ftrain.files import replace_text

STORAGE_FILE = "storage.txt"
"""In a log directory: the storage whose run it holds the records of (``storage_key``)."""
RECORDS = ("metrics.csv", "config.yaml", "run.json", "events.jsonl")
"""What a run records in its log directory: a directory with none of them belongs to no storage yet (a run refused
before it trained, say)."""


@contextlib.contextmanager
def claim_log_dir(log_dir: Path, node: int | None, holder: str, storage: str) -> Iterator[None]:
    """Hold ``log_dir`` for this run (``node``: this node's number on several nodes, else None; ``holder``: what
    holds it, e.g. "supervisor", shown to a run refused; ``storage``: the run's storage, ``storage_key``) for the
    ``with`` block; UserError naming the holder and the way out if another run holds it, or the other storage if it
    holds another storage's records.

    A run on one node holds ``run.lock`` alone; each node of a run on several holds ``run-node-N.lock`` alone and
    ``run.lock`` shared with the other nodes, so that neither kind of run starts beside the other."""
    log_dir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as held:
        if node is None:
            _hold(held, log_dir, "run.lock", fcntl.LOCK_EX, holder)
        else:
            _hold(held, log_dir, "run.lock", fcntl.LOCK_SH, None)
            _hold(held, log_dir, f"run-node-{node}.lock", fcntl.LOCK_EX, holder)
        _belongs(log_dir, storage)
        yield


def _belongs(log_dir: Path, storage: str) -> None:
    """Record that ``log_dir`` holds the records of ``storage``; UserError if it holds another storage's. A local
    storage's own directory, its default log directory, is its own whatever it was called before (moved), and a
    directory without records is anyone's. (A storage made in another run's log directory, which holds no steps of
    its own while that run's storage is still there, would rewrite them: refused.)"""
    record = log_dir / STORAGE_FILE
    try:
        other = record.read_text().strip()
    except FileNotFoundError:
        other = ""  # a new log directory, or one of an ftrain that kept no record: this run's from now on
    except OSError as error:
        raise _cannot_hold(log_dir, record, error) from None
    held = [name for name in RECORDS if (log_dir / name).exists()]
    own = os.path.realpath(log_dir) == storage and os.path.isabs(other)  # moved, or copied with its steps
    if (
        other in ("", storage)
        or not held
        or (own and (not os.path.exists(other) or (log_dir / "checkpoints").is_dir()))
    ):
        if other != storage:
            with contextlib.suppress(OSError):  # a directory it cannot write is said when a record is written
                replace_text(record, storage + "\n")
        return
    raise UserError(
        f"log directory {log_dir} holds the records of the run on {other} (its {', '.join(held)}): give the "
        f"run on {storage} a log directory of its own with log_dir=DIR (if that storage has moved to {storage}, delete "
        f"{record} first)"
    )


def _hold(held: contextlib.ExitStack, log_dir: Path, name: str, mode: int, holder: str | None) -> None:
    """``flock`` ``log_dir/name`` in ``mode`` until ``held`` closes; an exclusive holder writes its name in the file."""
    path = log_dir / name
    try:
        lock = held.enter_context(path.open("a+"))
    except OSError as error:
        raise _cannot_hold(log_dir, path, error) from None
    try:
        fcntl.flock(lock, mode | fcntl.LOCK_NB)
        lock.truncate(0)  # a shared holder clears the name of an exclusive one gone
        if holder is not None:
            lock.write(f"{holder} pid {os.getpid()} on {socket.gethostname()}\n")  # for a run refused to read
        lock.flush()
    except BlockingIOError:
        # a run on one node wrote its name; where none is written, the nodes of a run on several hold it shared
        holders = _held_names([path]) or _held_names(log_dir.glob("run-node-*.lock")) or "another run"
        raise UserError(
            f"log directory {log_dir} is in use by another run ({holders}): stop that run, or give this one a log "
            "directory of its own with log_dir=DIR"
        ) from None
    except OSError as error:  # no locks on that file system, a full disk
        raise _cannot_hold(log_dir, path, error) from None


def _held_names(paths: Iterable[Path]) -> str:
    """The names written in those of ``paths`` that a process holds now (a lock file left by a run gone is not)."""
    said = []
    for path in sorted(paths):
        with contextlib.suppress(OSError), path.open() as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_SH | fcntl.LOCK_NB)
                fcntl.flock(lock, fcntl.LOCK_UN)
            except BlockingIOError:
                said += [line for line in lock.read().splitlines() if line]
    return ", ".join(said)


def _cannot_hold(log_dir: Path, path: Path, error: OSError) -> UserError:
    """A lock file that is not ours to write, a file system without locks, a full disk."""
    return UserError(
        f"log directory {log_dir} cannot be held ({path}: {error.strerror or error}): give this run a log directory "
        "on a local file system you can write, with log_dir=DIR"
    )
