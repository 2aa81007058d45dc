"""``ftrain supervise``'s options, exit codes and their parsing (one-line errors for bad values).

Exit codes: ``EXIT_CODES`` (``ftrain supervise --help`` lists them; so does the README).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

from ftrain.errors import (
    EXIT_INTERRUPTED,
    EXIT_PREEMPTED,
    EXIT_RENDEZVOUS_TIMEOUT,
    EXIT_STORAGE_DOWN,
    EXIT_STORAGE_HELD,
    EXIT_USAGE,
    UserError,
)
from ftrain.supervise.auth import load_secret

EXIT_DONE = 0
EXIT_CRASH_LOOP = 3
EXIT_MAX_RESTARTS = 4
EXIT_PEER_LOST = 5
EXIT_TOO_FEW_NODES = EXIT_RENDEZVOUS_TIMEOUT
EXIT_STORAGE_WAIT = EXIT_STORAGE_DOWN

EXIT_CODES = {
    EXIT_DONE: "training finished",
    EXIT_USAGE: "bad input (config, options, or a worker refused its input); nothing restarted",
    EXIT_CRASH_LOOP: "crash loop: --crash-loop restarts in a row committed no new checkpoint",
    EXIT_MAX_RESTARTS: "--max-restarts exhausted",
    EXIT_PEER_LOST: "several nodes: node 0's supervisor unreachable for --rdzv-timeout seconds",
    EXIT_TOO_FEW_NODES: "elastic: fewer than MIN nodes joined within --rdzv-timeout seconds; nothing committed lost",
    EXIT_STORAGE_WAIT: "the checkpoint storage did not answer for --storage-wait seconds; nothing committed lost",
    EXIT_STORAGE_HELD: "another run holds the storage (its lease); nothing of that run touched",
    EXIT_INTERRUPTED: "interrupted (SIGINT, Ctrl-C): the workers saved; run the same command again to continue",
    EXIT_PREEMPTED: "preempted (SIGTERM): the workers saved; run the same command again to continue",
}
"""Every exit code of ``ftrain supervise`` and what it means. Until ``--storage-wait`` runs out, an unreachable storage
is waited out, and restarts for it count neither towards ``--max-restarts`` nor the crash loop."""


def exit_codes_help() -> str:
    """The exit codes and the stop signals, for ``ftrain supervise --help``."""
    codes = "\n".join(f"  {code:>3}  {meaning}" for code, meaning in EXIT_CODES.items())
    return (
        "SIGTERM or SIGINT (Ctrl-C) to the supervisor makes the workers save at the next iteration boundary\n"
        "and exit; the supervisor then exits 143 or 130. A second signal stops them at once.\n\nexit codes:\n" + codes
    )


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
