"""One supervisor per node and log directory.

The log directory holds what is this run's alone on this machine: ``events.jsonl``, ``metrics.csv``, the heartbeats
(which the supervisor clears for a new attempt and whose pids it kills), the spool (which prunes steps it did not
write) and the attempts' logs. Two runs sharing one would corrupt each other's records and kill each other's workers,
so a supervisor holds an exclusive ``flock`` on ``<log_dir>/supervisor[-node-N].lock`` while it runs (the kernel drops
it with the process, however it ends) and a second one is refused with one line. Several nodes of one run on one host
share the directory, one lock each.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path
from typing import IO

from ftrain.errors import UserError


def claim_log_dir(log_dir: Path, node: int | None) -> IO[str]:
    """Hold ``log_dir`` for this supervisor (``node``: its node number on several nodes, else None) until the returned
    file is closed or the process ends; UserError naming the holder and the way out if another supervisor holds it."""
    log_dir.mkdir(parents=True, exist_ok=True)
    path = log_dir / f"supervisor{'' if node is None else f'-node-{node}'}.lock"
    lock = path.open("a+")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock.seek(0)
        holder = lock.read().strip() or "another supervisor"
        lock.close()
        raise UserError(
            f"log directory {log_dir} is in use by another run ({holder}): stop that run, or give this one a log "
            "directory of its own with log_dir=DIR"
        ) from None
    lock.truncate(0)
    lock.write(f"supervisor pid {os.getpid()}\n")
    lock.flush()
    return lock
