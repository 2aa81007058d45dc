"""Process titles: what ``ps``, ``top`` and ``py-spy`` show for each process of a run, e.g. ``ftrain: rank 1/2 worker
(run hc)`` instead of ``python -u -m ftrain.warm serve`` for a warm worker (setproctitle, as gunicorn, Ray and Celery
name theirs). The title replaces what ``/proc/<pid>/cmdline`` shows, within the length of the command line it
replaces (``SPT_NOENV``): a longer one would overwrite the memory that ``/proc/<pid>/environ`` shows, where the
supervisor finds the processes of an attempt by their token (``supervise/attempt.py``). ``sys.argv`` stays."""

from __future__ import annotations

import os

os.environ["SPT_NOENV"] = "1"  # read when setproctitle is imported
from setproctitle import setproctitle, setthreadtitle

AGENT = "torchrun agent"
"""The role of torchrun's agent (``ftrain.torchrun``), which the supervisor finds by its title when the warm pool
forked it."""


def title(role: str, run: str | None = None) -> str:
    return f"ftrain: {role}" + (f" (run {run})" if run else "")


def name_process(role: str, run: str | None = None) -> None:
    """The title ``ftrain: ROLE (run RUN)``; the process's short name (``/proc/<pid>/comm``, 15 bytes, what ``top``
    shows by default) ``ftrain-ROLE`` without spaces: tools that split ``/proc/<pid>/stat`` at spaces (SLURM's
    proctrack/linuxproc among them) lose a process whose name has one, and with it its children, which then miss the
    signals of a time limit or a requeue."""
    setproctitle(title(role, run))
    setthreadtitle("ftrain-" + role.replace("rank ", "r").replace("/", "of").replace(" ", "-"))


def rank_role(kind: str) -> str:
    """``rank R/W KIND`` from torchrun's environment of this process (``KIND`` alone outside torchrun)."""
    rank, world = os.environ.get("RANK"), os.environ.get("WORLD_SIZE")
    return f"rank {rank}/{world} {kind}" if rank is not None and world is not None else kind
