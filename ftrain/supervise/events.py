"""``events.jsonl``: one JSON line per supervisor decision, the ones with a message printed as well.

Record. One JSON line per decision in ``<log_dir>/events.jsonl``: ``start``, ``resumed``, ``worker_died``, ``exit``,
``world`` (how many workers, where ``--nproc-per-node`` was left out), ``hang``, ``superseded``, ``regroup`` (etcd-v2,
elastic: another node left, preempted; this node's workers saved and it goes on without it), ``restart``,
``recovered``, ``storage_wait`` and ``storage_back`` (an unreachable storage waited out: why, how long), ``resize``
(the world size changed: old and new world and nodes, why, the step resumed from, iterations lost, downtime),
``preempt``, ``refused`` (node 0: a connection that brought no signed request), ``undead`` (a process of an ended
attempt outlives its SIGKILL: the next attempt waits), ``absent`` (the supervisor itself did not run for a while:
stopped, suspended), ``lease`` (the storage's lease taken over from a run that is gone, lost to another run, or not
renewed: ``detail``), and the ending (``done``, ``preempted``, ``crash_loop``, ``max_restarts``, ``usage``,
``peer_lost``, ``peer_ended``, ``too_few_nodes``, ``not_admitted`` (elastic: this node alone found no worker group),
``storage_down``), then ``summary`` (restarts, iterations lost, downtime).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from ftrain.redact import display_urls


class EventLog:
    """Appends one JSON line per decision; decisions with a message are also printed."""

    def __init__(self, path: Path, node: int | None) -> None:
        """Nothing is created before the first record (bad input found meanwhile leaves no directory behind)."""
        self.path = path
        self.node = node
        self.unwritable = False
        """Whether the last record could not be written (said once until one is written again)."""

    def __call__(self, event: str, message: str = "", **fields) -> None:
        record = {"time": round(time.time(), 3), "event": event, **display_urls(fields)}  # json writes a Url raw
        if self.node is not None:
            record["node"] = self.node
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with self.path.open("a") as file:
                file.write(json.dumps(record) + "\n")
        except OSError as error:  # a full disk must not end the supervisor (and its run): the line still goes out
            if not self.unwritable:
                print(
                    f"ftrain supervise: cannot write {self.path} ({error}): decisions go to stderr only",
                    file=sys.stderr,
                )
            self.unwritable = True
        else:
            self.unwritable = False
        if message:
            print(f"ftrain supervise: {message}", file=sys.stderr, flush=True)
