"""Several nodes. The same command on every node with ``--nnodes N --node-rank R --rdzv-endpoint HOST:PORT`` where
HOST is node 0's address. Node 0's supervisor listens on PORT and names the current attempt and a fresh port for
its torchrun rendezvous (node 0's torchrun hosts the store there). A node whose attempt fails tells node 0, which
moves everyone to the next attempt on a new port; the other nodes see that within half a second and restart too.
So no node can join the store of a dead attempt, and all nodes restart exactly once per failure. With
``--nnodes MIN:MAX`` the rendezvous is torchrun's elastic one (see ``rendezvous_args``): which nodes train, and
with how many ranks, is torchrun's decision; the coordinator only numbers the attempts. Node 0 must live: it
answers the other nodes and hosts the rendezvous (as torchrun's c10d endpoint host must).

Node 0 listens on the address of ``--rdzv-endpoint`` only, and answers only requests signed with the run's secret
(``auth.py``; they also name the plan's generation, so a request recorded in an earlier run does nothing now). It
makes the plan once it holds the storage's lease, at the next generation (``identity.py``): until then it answers
that it is starting. Anything
else (a wrong secret, garbage, a line over ``auth.MAX_MESSAGE`` bytes, a client slower than ``CONNECTION_TIMEOUT``)
is refused and recorded as a ``refused`` event; one connection is served per thread, so a slow one stalls nobody.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import secrets
import socket
import socketserver
import threading
import time
from collections.abc import Callable

from ftrain.ckpt.lease import Lease
from ftrain.errors import UserError
from ftrain.supervise.auth import HOW_TO_SET, REPLY, REQUEST, Refused, read_line, seal, unseal
from ftrain.supervise.options import EXIT_DONE, Nodes, SupervisorOptions
from ftrain.supervise.plan import Plan, apply, elastic_rendezvous

POLL = 0.1
"""Seconds between two looks at whether every node has learnt the outcome."""
CONNECTION_TIMEOUT = 5.0
"""Seconds a connection to node 0 may take to deliver its request, or a reply to come back."""
MAX_LOGGED_REFUSALS = 1000
"""Refused connections recorded in events.jsonl at most (a flood must not fill the disk)."""
OPS = ("plan", "fail", "leave", "finish")
STARTING = b"starting\n"
"""Node 0's answer before it has made the plan (it is taking the storage's lease)."""
GONE_AFTER = 3.0
"""Seconds without a request after which node 0 no longer waits for a node to learn the outcome."""


class Coordinator:
    """Node 0's record of the current attempt. On one node it is just the attempt counter.

    Requests change the plan by ``plan.apply``: a failure moves every node to the next attempt on a new rendezvous
    port, ``finish`` publishes the exit code that ends the run on every node.
    """

    def __init__(self, multi_node: bool, secret: bytes | None = None, log: Callable[..., None] | None = None) -> None:
        """``secret``: what requests from other nodes must be signed with; ``log``: records refusals (an EventLog)."""
        self._multi_node = multi_node
        self.secret = secret
        self._log = log
        self._lock = threading.Lock()
        self._plan: Plan | None = None
        self._informed: set[int] = set()
        self._seen: dict[int, float] = {}
        """When each node last asked (nodes of an elastic run may be gone for good)."""
        self._made = 0.0
        """When the plan was made (``begin``): a node that never asked since counts as silent from then."""
        self._refusals: dict[str, int] = {}
        """Refused connections so far, by reason."""
        self._server: _Server | None = None

    def begin(self, generation: int) -> None:
        """Make the run's plan at ``generation``, which this node took as the plan's maker (``Lease.hold``)."""
        with self._lock:
            self._plan = Plan(generation, 0, self._port())
            self._made = time.monotonic()

    @property
    def generation(self) -> int | None:
        """The plan's generation (None before ``begin``): every request that changes the plan must name it."""
        return self._plan.generation if self._plan is not None else None

    def _port(self) -> int | None:
        return free_port() if self._multi_node else None

    def handle(self, request: dict) -> dict | None:
        """The plan after ``request``; None before ``begin``."""
        with self._lock:
            if self._plan is None:
                return None
            self._plan = plan = apply(self._plan, request, self._port)
            if plan.final is not None:
                self._informed.add(request["node"])
            self._seen[request["node"]] = time.monotonic()
            return dataclasses.asdict(plan)

    def serve(self, host: str, port: int) -> socketserver.TCPServer:
        """Answer the other nodes on ``host:port`` (the address of ``--rdzv-endpoint``, not every interface)."""
        try:
            server = _Server((host, port), _Handler)
        except OSError as error:
            raise UserError(
                f"--rdzv-endpoint: node 0 cannot listen on {host}:{port} ({error.strerror}): pass an address of "
                "node 0 that the other nodes reach, and a free port"
            ) from None
        server.coordinator = self
        threading.Thread(target=server.serve_forever, args=(POLL,), daemon=True).start()
        self._server = server
        return server

    def close(self) -> None:
        """Stop answering (if serving)."""
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()

    def refuse(self, peer: tuple[str, int], reason: str) -> None:
        """A connection that brought no signed request of this run: a ``refused`` event (the first of each reason
        printed too), up to ``MAX_LOGGED_REFUSALS`` of them."""
        with self._lock:
            first = reason not in self._refusals
            self._refusals[reason] = self._refusals.get(reason, 0) + 1
            logged = sum(self._refusals.values()) <= MAX_LOGGED_REFUSALS
        if self._log is not None and logged:
            message = f"refused a connection from {peer[0]}: {reason} (see events.jsonl for more)" if first else ""
            self._log("refused", message, peer=f"{peer[0]}:{peer[1]}", reason=reason)

    def wait_informed(self, nnodes: int, timeout: float) -> None:
        """Until every node has learnt the outcome, at most ``timeout`` seconds; a node silent for ``GONE_AFTER``
        seconds is not waited for (an elastic run went on without it), nor, when the run finished, one that has not
        asked since the plan was made that long ago: a finished run's end is in the storage, where a node started
        again after it finds it without asking (another ending it can learn from node 0 alone)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                now = time.monotonic()
                never = self._made if self._plan is not None and self._plan.final == EXIT_DONE else math.inf
                silent = {node for node in range(nnodes) if now - self._seen.get(node, never) > GONE_AFTER}
                if self._informed | silent >= set(range(nnodes)):
                    return
            time.sleep(POLL)


class _Server(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = True
    coordinator: Coordinator


class _Handler(socketserver.BaseRequestHandler):
    """One signed request per connection, read within ``CONNECTION_TIMEOUT``; its reply signed too."""

    def handle(self) -> None:
        coordinator = self.server.coordinator
        try:
            request = unseal(coordinator.secret, REQUEST, read_line(self.request, CONNECTION_TIMEOUT))
            if not _well_formed(request):
                raise Refused("malformed")
            plan = coordinator.handle(request)
            reply = seal(coordinator.secret, REPLY, {**plan, "nonce": request["nonce"]}) if plan else STARTING
        except Refused as refused:
            coordinator.refuse(self.client_address, str(refused))
            with contextlib.suppress(OSError):  # unsigned: a hint for a node with the wrong secret, nothing more
                self.request.sendall(f"refused: {refused}\n".encode())
            return
        with contextlib.suppress(OSError):
            self.request.sendall(reply)


def _well_formed(request: dict) -> bool:
    return (
        request.get("op") in OPS
        and type(request.get("node")) is int
        and isinstance(request.get("nonce"), str)
        and (request["op"] != "finish" or type(request.get("code")) is int)
    )


class Link:
    """This node's line to the coordinator (``link.PlanLink``): a direct call on node 0, one signed TCP request per
    question elsewhere. Every request names the plan's generation (node 0 knows it; the others learn it from the
    first reply). Node 0's link holds the coordinator: it makes the plan, serves the others and closes with it."""

    def __init__(
        self, node: int, coordinator: Coordinator | None, address: tuple[str, int] | None, secret: bytes | None
    ) -> None:
        self.node = node
        self.coordinator = coordinator
        self.address = address
        self.peer = "node 0 at {}:{}".format(*address) if address else "node 0"
        self.secret = secret
        self.generation: int | None = None

    def begin(self, lease: Lease) -> None:
        """Node 0 (or one node alone) makes the plan at the generation of the ``lease`` it holds; the other nodes
        learn it from node 0's first reply."""
        if self.coordinator is not None:
            self.coordinator.begin(lease.generation)

    def settle(self, nnodes: int, timeout: float) -> None:
        """Node 0: until every node has learnt the run's end (``Coordinator.wait_informed``)."""
        if self.coordinator is not None:
            self.coordinator.wait_informed(nnodes, timeout)

    def close(self) -> None:
        if self.coordinator is not None:
            self.coordinator.close()

    def ask(self, op: str, **fields) -> Plan:
        """Raises OSError when node 0 cannot be reached, is starting, or refuses the request."""
        if self.coordinator is not None:
            self.generation = self.coordinator.generation
        request = {"op": op, "node": self.node, "generation": self.generation, **fields}
        if self.coordinator is not None:
            if (plan := self.coordinator.handle(request)) is None:
                raise ConnectionError(f"{self.peer} is starting")
            return Plan(**plan)
        nonce = secrets.token_hex(8)
        with socket.create_connection(self.address, timeout=CONNECTION_TIMEOUT) as conn:
            conn.sendall(seal(self.secret, REQUEST, {**request, "nonce": nonce}))
            line = read_line(conn, CONNECTION_TIMEOUT)
        if line + b"\n" == STARTING:
            raise ConnectionError(f"{self.peer} is starting")
        if line.startswith(b"refused: "):
            reason = line.removeprefix(b"refused: ").decode(errors="replace")
            raise Refused(f"node 0 refused this node's request ({reason}): {HOW_TO_SET}")
        reply = unseal(self.secret, REPLY, line)
        if reply.pop("nonce", None) != nonce:
            raise Refused("node 0's reply answers another request")
        plan = Plan(**reply)
        self.generation = plan.generation
        return plan


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("", 0))
        return sock.getsockname()[1]


def rendezvous_args(plan: Plan, nodes: Nodes, options: SupervisorOptions) -> list[str]:
    """torchrun's rendezvous for ``plan``, under a run id of this attempt; node 0's torchrun hosts the store on the
    plan's fresh port.

    A fixed number of nodes meets in a static rendezvous: node R runs global ranks R x nproc and up, every time.
    Elastic (``MIN:MAX``) nodes meet in torchrun's c10d rendezvous (``plan.elastic_rendezvous``).
    """
    run_id = f"ftrain-g{plan.generation}-{plan.attempt}"
    if not nodes.elastic:
        return [
            f"--nnodes={nodes.count}",
            f"--node-rank={options.node_rank}",
            "--rdzv-backend=static",
            f"--master-addr={nodes.endpoint[0]}",
            f"--master-port={plan.port}",
            f"--rdzv-id={run_id}",
            f"--rdzv-conf=timeout={math.ceil(options.rdzv_timeout)}",
        ]
    endpoint = f"{nodes.endpoint[0]}:{plan.port}"
    is_host = int(options.node_rank == 0)  # on one machine (tests) every node would match the host's address
    return elastic_rendezvous("c10d", plan, endpoint, run_id, nodes, options, is_host=is_host)
