"""``ftrain supervise``'s options, exit codes and their parsing (one-line errors for bad values).

Exit codes: ``EXIT_CODES`` (``ftrain supervise --help`` lists them; so does docs/supervision.md).
"""

from __future__ import annotations

import enum
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

from ftrain import procfs
from ftrain.errors import (
    EXIT_INTERRUPTED,
    EXIT_PREEMPTED,
    EXIT_RENDEZVOUS_TIMEOUT,
    EXIT_STORAGE_DOWN,
    EXIT_STORAGE_HELD,
    EXIT_USAGE,
    UserError,
    did_you_mean,
)
from ftrain.supervise.address import interface_of
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
    EXIT_PEER_LOST: "several nodes: node 0's supervisor (c10d) or etcd unreachable for --rdzv-timeout seconds",
    EXIT_TOO_FEW_NODES: "elastic: fewer than MIN nodes joined within --rdzv-timeout seconds, or the nodes training "
    "did not take this one in (it came back late: it ends alone); nothing committed lost",
    EXIT_STORAGE_WAIT: "the checkpoint storage did not answer, or a disk of the run stayed full, for --storage-wait "
    "seconds; nothing committed lost",
    EXIT_STORAGE_HELD: "another run holds the storage (its lease): nothing of that run touched; or it took the storage "
    "from this run (a newer lease generation) and this run committed nothing more",
    EXIT_INTERRUPTED: "interrupted (SIGINT, Ctrl-C): the workers saved; run the same command again to continue",
    EXIT_PREEMPTED: "preempted (SIGTERM): the workers saved; run the same command again to continue (elastic, MIN "
    "nodes left, on etcd-v2 or c10d's nodes but 0: this node left, the others go on)",
}
"""Every exit code of ``ftrain supervise`` and what it means. Until ``--storage-wait`` runs out, an unreachable storage
is waited out, and restarts for it count neither towards ``--max-restarts`` nor the crash loop."""


def exit_codes_help() -> str:
    """The exit codes and the stop signals, for ``ftrain supervise --help``."""
    codes = "\n".join(f"  {code:>3}  {meaning}" for code, meaning in EXIT_CODES.items())
    return (
        "SIGTERM, SIGHUP (a closed terminal) or SIGINT (Ctrl-C) to the supervisor makes the workers save at the\n"
        "next iteration boundary and exit; the supervisor then exits 143 (130 for SIGINT). A second signal, half a\n"
        "second or more after the first, stops them at once, without a save (the summary counts the iterations\n"
        "lost).\n\nexit codes:\n" + codes
    )


BACKOFF_INITIAL = 1.0
"""Seconds of the first back-off where ``--backoff-initial`` is not given."""
WORKER_MEMORY = 50 * 10**6
"""The least memory a worker takes of its own, forked from the warm pool (its stand-in, gloo's buffers, the model,
a few environments): more workers than the machine has memory available for are refused before any starts."""


@dataclass
class SupervisorOptions:
    nproc_per_node: int | None = field(
        default=1,
        metadata={
            "help": "worker processes on this node",
            "unset": "on one node, as many as the run's newest checkpoint was trained with, else 1",
        },
    )
    """None (the command line without --nproc-per-node): ``supervise`` sets it from the storage (``with_nproc``)."""
    nnodes: str = field(
        default="1",
        metadata={"help": "number of nodes, or MIN:MAX to go on with fewer (elastic); the same command on every node"},
    )
    node_rank: int = field(
        default=0, metadata={"help": "c10d: this node's rank, 0 .. nnodes-1 (node 0 coordinates); etcd-v2: not used"}
    )
    rdzv_backend: str = field(
        default="c10d",
        metadata={
            "help": "several nodes: c10d (node 0 hosts the rendezvous and coordinates: it must live) or etcd-v2 "
            "(an etcd server outside the nodes holds both: any node may be lost)"
        },
    )
    rdzv_endpoint: str = field(
        default="",
        metadata={
            "help": "several nodes: HOST:PORT; c10d: node 0's address and a free port for its supervisor; etcd-v2: "
            "etcd's client address (HOST:2379)"
        },
    )
    rdzv_id: str = field(default="", metadata={"help": "etcd-v2: the run's name, the same on every node"})
    local_addr: str = field(
        default="",
        metadata={
            "help": "several nodes: this node's address as the others reach it (torchrun's --local-addr; default: "
            "what its hostname resolves to): the workers' store listens there when this node has rank 0, and gloo "
            "binds to the interface that holds it"
        },
    )
    rdzv_conf: str = field(
        default="",
        metadata={
            "help": "etcd-v2: connection settings as torchrun's --rdzv-conf names them, KEY=VALUE,...: protocol "
            "(http or https), ca_cert, ssl_cert, ssl_cert_key (file paths), read_timeout (seconds)"
        },
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
    backoff_initial: float | None = field(
        default=None,
        metadata={
            "help": "seconds before restarting an attempt that completed no iteration (doubles each time); default 1, "
            "at most --backoff-max"
        },
    )
    backoff_max: float = field(default=60.0, metadata={"help": "longest back-off in seconds"})
    crash_loop: int = field(
        default=3, metadata={"help": "stop (exit 3) after this many restarts in a row commit no new step (0: never)"}
    )
    storage_wait: float | None = field(
        default=None,
        metadata={
            "help": "seconds to wait for an unreachable checkpoint storage before giving up (exit 7); default 3600, "
            "300 for one that has not answered since the command started (a wrong URL or endpoint, more likely)"
        },
    )
    stop_grace: float = field(
        default=30.0, metadata={"help": "seconds between SIGTERM and SIGKILL when stopping workers (time to save)"}
    )
    workers: str = field(
        default="warm",
        metadata={
            "help": "warm: fork each worker from a process of this node that imported torch, rsl-rl and MuJoCo once "
            "(a restart skips seconds of imports; see ftrain/warm); cold: a fresh Python process per worker"
        },
    )

    def __post_init__(self) -> None:
        """Every numeric option in its range, refused in one line as the options are built, before anything starts;
        a first back-off given above the longest; ``--node-rank`` against ``--nnodes``: ``parse_nodes``."""
        parse_hang_timeout(self.hang_timeout)
        inf = math.inf
        ranges = {  # option: (low, high, whether low itself is allowed, what to use)
            "nproc_per_node": (1, inf, True, "1 or more worker processes"),
            "node_rank": (0, inf, True, "0 to --nnodes minus 1"),
            "rdzv_timeout": (0, inf, False, "a positive number of seconds, e.g. 600"),
            "rejoin_timeout": (0, inf, True, "0 or more seconds, e.g. 30"),
            "max_restarts": (0, inf, True, "0 (never restart) or more, e.g. 10"),
            "startup_grace": (0, inf, False, "a positive number of seconds, e.g. 300"),
            "backoff_max": (0, inf, True, "0 or more seconds, e.g. 60"),
            "backoff_initial": (0, inf, True, "0 or more seconds, e.g. 1"),
            "crash_loop": (0, inf, True, "0 (never stop for a crash loop) or more restarts, e.g. 3"),
            "storage_wait": (0, inf, True, "0 (do not wait) or more seconds, e.g. 3600"),
            "stop_grace": (0, inf, False, "a positive number of seconds, e.g. 30"),
        }
        for name, (low, high, closed, what) in ranges.items():
            value = getattr(self, name)
            if value is None:  # the defaults of --storage-wait (outage.WAITS), --backoff-initial, --nproc-per-node
                continue
            if not math.isfinite(value) or not (low <= value <= high if closed else low < value <= high):
                raise UserError(f"--{name.replace('_', '-')}={value} is out of range: use {what}")
        available = procfs.available_memory()
        if available is not None and (self.nproc_per_node or 0) * WORKER_MEMORY > available:
            raise UserError(
                f"--nproc-per-node={self.nproc_per_node}: that many workers need at least "
                f"{self.nproc_per_node * WORKER_MEMORY / 1e9:.1f} GB of memory ({WORKER_MEMORY // 10**6} MB each), and "
                f"this machine has {available / 1e9:.1f} GB available: use --nproc-per-node="
                f"{max(available // WORKER_MEMORY, 1)} or fewer"
            )
        if self.backoff_initial is None:  # not given: --backoff-max 0 alone is no back-off
            self.backoff_initial = min(BACKOFF_INITIAL, self.backoff_max)
        if self.backoff_initial > self.backoff_max:
            raise UserError(
                f"--backoff-initial={self.backoff_initial} is more than --backoff-max={self.backoff_max}: the first "
                "back-off is at most the longest, raise --backoff-max or lower --backoff-initial"
            )


class Workers(enum.StrEnum):
    """How an attempt's workers start: forked from the node's warm pool, or as fresh processes."""

    WARM = "warm"
    COLD = "cold"


def parse_workers(value: str) -> Workers:
    if value not in tuple(Workers):
        raise UserError(f"--workers={value!r} must be one of {', '.join(Workers)}{did_you_mean(value, Workers)}")
    return Workers(value)


def parse_hang_timeout(value: str) -> float | None:
    if value == "auto":
        return None
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not 0 < seconds < math.inf:  # inf, 1e400: no hang would ever be caught, without a word
        raise UserError(f"--hang-timeout={value!r} must be auto or a positive number of seconds")
    return seconds


class Backend(enum.Enum):
    """Where the nodes of a run meet: node 0 (torchrun's c10d store and ftrain's coordinator) or an etcd server."""

    C10D = "c10d"
    ETCD = "etcd-v2"


ETCD_CONF = {
    "protocol": ("http", "https"),
    "ca_cert": Path,
    "ssl_cert": Path,
    "ssl_cert_key": Path,
    "read_timeout": int,
}
"""The etcd connection settings ``--rdzv-conf`` takes (torch's etcd-v2 names): allowed values, a file or a number."""


@dataclass(frozen=True)
class Nodes:
    count: int
    """The most nodes the run has (``--nnodes N``: N, ``MIN:MAX``: MAX)."""
    least: int = 1
    """The fewest nodes it trains on: ``count`` unless elastic."""
    endpoint: tuple[str, int] | None = None
    """Several nodes: ``(host, port)`` of node 0 (c10d) or of etcd (etcd-v2)."""
    secret: bytes | None = None
    """c10d: what the nodes' messages to node 0 and its replies are signed with."""
    backend: Backend = Backend.C10D
    run_id: str = ""
    """etcd-v2: the run's name (``--rdzv-id``)."""
    conf: tuple[tuple[str, str], ...] = ()
    """etcd-v2: the connection settings of ``--rdzv-conf``."""
    interface: str = ""
    """Several nodes with ``--local-addr``: the network interface that holds it, for the workers' gloo."""

    @property
    def run_key(self) -> bytes | None:
        """What the nodes of one run share, and no other run: the secret (c10d) or the run's name (etcd-v2)."""
        return self.run_id.encode() if self.backend is Backend.ETCD else self.secret

    @property
    def lease_endpoint(self) -> tuple[str, int] | None:
        """What names the run for the storage's lease besides ``run_key``: node 0's endpoint (c10d); none on etcd,
        whose address each node may spell its own way."""
        return None if self.backend is Backend.ETCD else self.endpoint

    @property
    def elastic(self) -> bool:
        return self.least < self.count


def parse_nodes(options: SupervisorOptions) -> Nodes:
    least, _, most = options.nnodes.partition(":")
    most = most or least
    if not (least.isdecimal() and most.isdecimal() and 1 <= int(least) <= int(most)):
        raise UserError(f"--nnodes={options.nnodes!r} must be a number of nodes N, or MIN:MAX with 1 <= MIN <= MAX")
    least, nnodes = int(least), int(most)
    backends = {backend.value: backend for backend in Backend}
    if options.rdzv_backend not in backends:
        raise UserError(
            f"--rdzv-backend={options.rdzv_backend!r} must be one of {', '.join(backends)}"
            f"{did_you_mean(options.rdzv_backend, backends)}"
        )
    backend = backends[options.rdzv_backend]
    if backend is Backend.C10D and options.rdzv_conf:
        raise UserError("--rdzv-conf is for --rdzv-backend etcd-v2 (c10d takes no connection settings): drop it")
    conf = parse_etcd_conf(options.rdzv_conf)  # checked on one node too, where it has no use: a typo is told now
    if (nnodes == 1 or backend is Backend.C10D) and options.node_rank >= nnodes:  # etcd-v2's nodes: not used
        ranks = "0 on one node" if nnodes == 1 else f"0 to {nnodes - 1}, one per node"
        raise UserError(f"--node-rank={options.node_rank} is out of range for --nnodes={options.nnodes}: use {ranks}")
    if nnodes == 1:
        return Nodes(1)
    host, _, port = options.rdzv_endpoint.rpartition(":")
    if not host or not (port.isdecimal() and 0 < int(port) < 65536):
        where = "etcd's client address" if backend is Backend.ETCD else "node 0's address and a free port"
        raise UserError(f"several nodes need --rdzv-endpoint=HOST:PORT (PORT 1 to 65535), {where}")
    interface = interface_of(options.local_addr) if options.local_addr else ""
    if backend is Backend.ETCD:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", options.rdzv_id):
            raise UserError("--rdzv-backend etcd-v2 needs --rdzv-id=NAME (letters, digits, _.-), alike on every node")
        return Nodes(
            nnodes, least, (host, int(port)), backend=backend, run_id=options.rdzv_id, conf=conf, interface=interface
        )
    return Nodes(
        nnodes, least, (host, int(port)), load_secret(options.rdzv_secret_file, os.environ), interface=interface
    )


def parse_etcd_conf(text: str) -> tuple[tuple[str, str], ...]:
    """``--rdzv-conf KEY=VALUE,...``: etcd connection settings only (the rendezvous timeouts come from
    ``--rejoin-timeout`` and ``--rdzv-timeout``); certificates and keys as files, never as values."""
    pairs = []
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        allowed = ETCD_CONF.get(key)
        if allowed is None:
            raise UserError(
                f"--rdzv-conf: {key!r} is not an etcd connection setting ({', '.join(ETCD_CONF)})"
                f"{did_you_mean(key, ETCD_CONF)}; the rendezvous timeouts come from --rejoin-timeout and --rdzv-timeout"
            )
        if allowed is Path and not Path(value).is_file():
            raise UserError(f"--rdzv-conf: {key}={value!r} must name a readable file (a PEM certificate or key)")
        if allowed is int and not (value.isdecimal() and int(value) > 0):
            raise UserError(f"--rdzv-conf: {key}={value!r} must be a positive whole number of seconds")
        if isinstance(allowed, tuple) and value not in allowed:
            raise UserError(
                f"--rdzv-conf: {key}={value!r} must be one of {', '.join(allowed)}{did_you_mean(value, allowed)}"
            )
        pairs.append((key, value))
    return tuple(pairs)
