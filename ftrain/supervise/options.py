"""``ftrain supervise``'s options, exit codes and their parsing (one-line errors for bad values).

Exit codes:

- 0: training finished.
- 2: bad input (config or options, or a worker exited with 2); nothing is restarted.
- 3: crash loop: ``--crash-loop`` restarts in a row committed no new checkpoint.
- 4: ``--max-restarts`` exhausted.
- 5: several nodes: node 0's supervisor was unreachable for ``--rdzv-timeout`` seconds.
- 6: elastic (``--nnodes MIN:MAX``): fewer than MIN nodes joined within ``--rdzv-timeout`` seconds. Nothing
  committed is lost: start the missing nodes and run the same command again.
- 7: the checkpoint storage did not answer for ``--storage-wait`` seconds. Nothing committed is lost: run the same
  command again once it is back. (Until then, an unreachable storage is waited out, and restarts for it count
  neither towards ``--max-restarts`` nor the crash loop.)
- 8: another run holds the storage's lease (``ftrain/ckpt/lease.py``): one line names it and when its lease ends;
  nothing of that run is touched, nothing is launched.
- 143: preempted (SIGTERM): the workers saved; run the same command again to continue. 128 + SIGTERM,
  so schedulers that retry signal exits (e.g. Kubernetes' ``ExitCode`` restart policy) run it again.
- 130: interrupted (SIGINT, Ctrl-C): the same as 143, with the shell's code for Ctrl-C.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from ftrain.errors import EXIT_RENDEZVOUS_TIMEOUT, EXIT_STORAGE_DOWN, UserError
from ftrain.supervise.auth import load_secret

EXIT_DONE = 0
EXIT_CRASH_LOOP = 3
EXIT_MAX_RESTARTS = 4
EXIT_PEER_LOST = 5
EXIT_TOO_FEW_NODES = EXIT_RENDEZVOUS_TIMEOUT
EXIT_STORAGE_WAIT = EXIT_STORAGE_DOWN


@dataclass
class SupervisorOptions:
    nproc_per_node: int = field(default=1, metadata={"help": "worker processes on this node"})
    nnodes: str = field(
        default="1",
        metadata={"help": "number of nodes, or MIN:MAX to go on with fewer (elastic); the same command on every node"},
    )
    node_rank: int = field(default=0, metadata={"help": "this node's rank, 0 .. nnodes-1 (node 0 coordinates)"})
    rdzv_endpoint: str = field(
        default="", metadata={"help": "several nodes: HOST:PORT, node 0's address and a free port for its supervisor"}
    )
    rdzv_secret_file: str = field(
        default="",
        metadata={"help": "several nodes: a file holding the run's shared secret (default: $FTRAIN_RDZV_SECRET)"},
    )
    rdzv_timeout: float = field(
        default=600.0,
        metadata={"help": "several nodes: seconds to wait for node 0 (then exit 5), elastic: for MIN nodes (exit 6)"},
    )
    rejoin_timeout: float = field(
        default=30.0,
        metadata={"help": "elastic: seconds a restart waits for more than MIN nodes (a lost node coming back)"},
    )
    max_restarts: int = field(default=10, metadata={"help": "restarts before giving up (exit 4)"})
    hang_timeout: str = field(
        default="auto",
        metadata={
            "help": "seconds every rank may stay silent in a phase before the group counts as hung, or auto: each "
            "phase 10x its longest time so far, at least 5 s (--startup-grace for a phase not seen yet)"
        },
    )
    startup_grace: float = field(
        default=300.0,
        metadata={
            "help": "seconds an attempt may take to reach its first iteration on every rank, and (hang timeout auto) "
            "its first iteration, or a phase not seen yet"
        },
    )
    backoff_initial: float = field(
        default=1.0,
        metadata={"help": "seconds before restarting an attempt that completed no iteration (doubles each time)"},
    )
    backoff_max: float = field(default=60.0, metadata={"help": "longest back-off in seconds"})
    crash_loop: int = field(
        default=3, metadata={"help": "stop (exit 3) after this many restarts in a row commit no new step (0: never)"}
    )
    storage_wait: float = field(
        default=3600.0,
        metadata={"help": "seconds to wait for an unreachable checkpoint storage before giving up (exit 7)"},
    )
    stop_grace: float = field(
        default=30.0, metadata={"help": "seconds between SIGTERM and SIGKILL when stopping workers (time to save)"}
    )


def parse_hang_timeout(value: str) -> float | None:
    if value == "auto":
        return None
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not seconds > 0:
        raise UserError(f"--hang-timeout={value!r} must be auto or a positive number of seconds")
    return seconds


@dataclass(frozen=True)
class Nodes:
    count: int
    """The most nodes the run has (``--nnodes N``: N, ``MIN:MAX``: MAX)."""
    least: int = 1
    """The fewest nodes it trains on: ``count`` unless elastic."""
    endpoint: tuple[str, int] | None = None
    """Several nodes: node 0's ``(host, port)``."""
    secret: bytes | None = None
    """Several nodes: what their messages to node 0 and its replies are signed with."""

    @property
    def elastic(self) -> bool:
        return self.least < self.count


def parse_nodes(options: SupervisorOptions) -> Nodes:
    least, _, most = options.nnodes.partition(":")
    most = most or least
    if not (least.isdigit() and most.isdigit() and 1 <= int(least) <= int(most)):
        raise UserError(f"--nnodes={options.nnodes!r} must be a number of nodes N, or MIN:MAX with 1 <= MIN <= MAX")
    least, nnodes = int(least), int(most)
    if options.nproc_per_node < 1:
        raise UserError(f"--nproc-per-node={options.nproc_per_node} must be at least 1")
    if not options.rejoin_timeout >= 0:
        raise UserError(f"--rejoin-timeout={options.rejoin_timeout} must be a number of seconds, 0 or more")
    if nnodes == 1:
        return Nodes(1)
    if not 0 <= options.node_rank < nnodes:
        raise UserError(f"--node-rank={options.node_rank} must be between 0 and {nnodes - 1}")
    host, _, port = options.rdzv_endpoint.rpartition(":")
    if not host or not port.isdigit():
        raise UserError("several nodes need --rdzv-endpoint=HOST:PORT, node 0's address and a free port")
    return Nodes(nnodes, least, (host, int(port)), load_secret(options.rdzv_secret_file, os.environ))
