"""One supervisor per node and log directory.

The log directory holds what is this run's alone on this machine: ``events.jsonl``, ``metrics.csv``, the heartbeats
(which the supervisor clears for a new attempt and whose pids it kills), the spool (which prunes steps it did not
write) and the attempts' logs. Two runs sharing one would corrupt each other's records and kill each other's workers,
so a supervisor holds an exclusive ``flock`` on ``<log_dir>/supervisor[-node-N].lock`` while it runs (the kernel drops
it with the process, however it ends) and a second one is refused with one line. It is taken after the storage's
lease: a second run on the same local storage (its log directory too) hears of the lease, which names the run.
Several nodes of one run on one host share the directory, one lock each.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from collections.abc import Iterator
from pathlib import Path

from ftrain.errors import UserError


@contextlib.contextmanager
def claim_log_dir(log_dir: Path, node: int | None) -> Iterator[None]:
    """Hold ``log_dir`` for this supervisor (``node``: its node number on several nodes, else None) for the ``with``
    block; UserError naming the holder and the way out if another supervisor holds it."""
    log_dir.mkdir(parents=True, exist_ok=True)
    path = log_dir / f"supervisor{'' if node is None else f'-node-{node}'}.lock"
    with path.open("a+") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            holder = lock.read().strip() or "another supervisor"
            raise UserError(
                f"log directory {log_dir} is in use by another run ({holder}): stop that run, or give this one a log "
                "directory of its own with log_dir=DIR"
            ) from None
        lock.truncate(0)
        lock.write(f"supervisor pid {os.getpid()}\n")
        lock.flush()
        yield
