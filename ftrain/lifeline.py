"""No process of a supervised run outlives its supervisor, however the supervisor ends (SIGKILL included); no worker
of a plain torchrun outlives its torchrun unsaved.

The supervisor names itself in ``FTRAIN_SUPERVISOR`` (its pid and start time: a pid the kernel hands out again has
another start time). torchrun, its child, asks the kernel for SIGKILL when its parent ends (``PR_SET_PDEATHSIG``),
then checks that its parent is still that supervisor (it may have ended before the request). The workers, torchrun's
children, must outlive a torchrun that dies alone (the supervisor then has them save: see ``supervise/supervisor.py``),
so a kernel tie to their parent does not fit them: each runs a thread that looks at the supervisor every ``POLL``
seconds and, once it is gone, SIGKILLs every process of its attempt (found by the attempt token, so a stopped sibling
too, which no thread of its own can end), itself last. Warm workers (``ftrain/warm``) carry the token in their
stand-ins, whose end makes the pool SIGKILL their forks; the pool itself dies with the supervisor, and its forks with
it. Without ``FTRAIN_SUPERVISOR`` (plain ``torchrun -m ftrain train``) a worker whose torchrun ends (SIGKILL
included) stops as if torchrun had stopped it: it SIGTERMs itself, and the ranks save and exit 143, so that no worker
trains on unseen, holding the storage against the next launch.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import sys
import threading
import time

from ftrain import procfs
from ftrain.heartbeat import TOKEN_ENV

SUPERVISOR_ENV = "FTRAIN_SUPERVISOR"
POLL = 0.5
"""Seconds between two looks of a worker at its supervisor."""
PR_SET_PDEATHSIG = 1
"""From ``<linux/prctl.h>``."""
TORCHRUN_ENV = "TORCHELASTIC_RUN_ID"
"""Set by torchrun in its workers' environment: a worker without it was not started by torchrun."""


def supervisor_env() -> dict[str, str]:
    """For the supervisor's attempts: names this process as their supervisor (nothing where ``/proc`` is missing)."""
    started = procfs.start_time(os.getpid())
    return {SUPERVISOR_ENV: f"{os.getpid()}:{started}"} if started else {}


def die_with_supervisor() -> None:
    """In torchrun (and the warm worker pool), first: SIGKILL from the kernel when the supervisor ends, or now if it
    already has."""
    supervisor = named_supervisor()
    if supervisor is not None:
        die_with_parent(supervisor[0])
        if not _alive(supervisor):
            os.kill(os.getpid(), signal.SIGKILL)


def die_with_parent(parent: int) -> None:
    """SIGKILL from the kernel when process ``parent``, this one's parent, ends; now if it already has (Linux)."""
    if not sys.platform.startswith("linux"):
        return
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG) failed")
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGKILL)


def watch_launcher() -> None:
    """In a worker: once the supervisor is gone, SIGKILL every process of this attempt, this one last; without a
    supervisor, once torchrun (this worker's parent) is gone, stop this rank as torchrun would (SIGTERM)."""
    supervisor, token = named_supervisor(), os.environ.get(TOKEN_ENV)
    if supervisor is not None and token:
        threading.Thread(target=_watch, args=(supervisor, token), name="ftrain-lifeline", daemon=True).start()
    elif supervisor is None and TORCHRUN_ENV in os.environ:
        threading.Thread(target=_watch_torchrun, args=(os.getppid(),), name="ftrain-lifeline", daemon=True).start()


def _watch_torchrun(torchrun: int) -> None:
    while os.getppid() == torchrun:
        time.sleep(POLL)
    if os.environ.get("LOCAL_RANK", "0") == "0":
        print(f"ftrain: torchrun (pid {torchrun}) ended under its workers: they save and exit", file=sys.stderr)
    os.kill(os.getpid(), signal.SIGTERM)


def _watch(supervisor: tuple[int, str], token: str) -> None:
    while _alive(supervisor):
        time.sleep(POLL)
    for pid in procfs.with_environment(TOKEN_ENV, token):
        if pid != os.getpid():
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
    os.kill(os.getpid(), signal.SIGKILL)


def named_supervisor() -> tuple[int, str] | None:
    """``(pid, start time)`` of the supervisor this process's environment names (``SUPERVISOR_ENV``), or None."""
    pid, _, started = os.environ.get(SUPERVISOR_ENV, "").partition(":")
    return (int(pid), started) if pid.isdigit() and started else None


def _alive(supervisor: tuple[int, str]) -> bool:
    """Whether that process still runs: a zombie (ended, not yet waited for by its parent) does not."""
    pid, started = supervisor
    fields = procfs.stat_fields(pid)
    return bool(fields) and fields[0] not in ("Z", "X") and fields[19] == started
