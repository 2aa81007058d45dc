"""Several nodes. The same command on every node with ``--nnodes N --node-rank R --rdzv-endpoint HOST:PORT`` where
HOST is node 0's address. Node 0's supervisor listens on PORT and names the current attempt and a fresh port for
its static rendezvous (node 0's torchrun hosts the store there). A node whose attempt fails tells node 0, which
moves everyone to the next attempt on a new port; the other nodes see that within half a second and restart too.
So no node can join the store of a dead attempt, and all nodes restart exactly once per failure.
"""

from __future__ import annotations

import dataclasses
import json
import math
import secrets
import socket
import socketserver
import threading
import time
from dataclasses import dataclass

from ftrain.errors import UserError
from ftrain.supervise.options import SupervisorOptions

POLL = 0.1
"""Seconds between two looks at whether every node has learnt the outcome."""


@dataclass
class Plan:
    """The attempt every node runs now, as node 0 decides; ``final`` is set once the run has ended."""

    token: str
    attempt: int
    port: int | None
    final: int | None = None


class Coordinator:
    """Node 0's record of the current attempt. On one node it is just the attempt counter.

    A failed attempt moves the plan to the next attempt and a new rendezvous port (only the first report of
    a failure counts); ``finish`` publishes the exit code that ends the run on every node.
    """

    def __init__(self, multi_node: bool) -> None:
        self._multi_node = multi_node
        self._lock = threading.Lock()
        self._plan = Plan(secrets.token_hex(4), 0, self._port())
        self._informed: set[int] = set()

    def _port(self) -> int | None:
        return free_port() if self._multi_node else None

    def handle(self, request: dict) -> dict:
        with self._lock:
            plan = self._plan
            current = request.get("token") == plan.token and request.get("attempt") == plan.attempt
            if request["op"] == "fail" and current and plan.final is None:
                self._plan = plan = Plan(plan.token, plan.attempt + 1, self._port())
            elif request["op"] == "finish" and plan.final is None:
                plan.final = request["code"]
            if plan.final is not None:
                self._informed.add(request["node"])
            return dataclasses.asdict(plan)

    def serve(self, port: int) -> socketserver.TCPServer:
        try:
            server = _Server(("", port), _Handler)
        except OSError as error:
            raise UserError(
                f"--rdzv-endpoint: cannot listen on port {port} ({error.strerror}): pick a free port"
            ) from None
        server.coordinator = self
        threading.Thread(target=server.serve_forever, args=(POLL,), daemon=True).start()
        return server

    def wait_informed(self, nnodes: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if self._informed >= set(range(nnodes)):
                    return
            time.sleep(POLL)


class _Server(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = True
    coordinator: Coordinator


class _Handler(socketserver.StreamRequestHandler):
    def handle(self) -> None:
        try:
            reply = self.server.coordinator.handle(json.loads(self.rfile.readline()))
        except (ValueError, KeyError, TypeError, AttributeError):
            return  # not one of ours
        self.wfile.write(json.dumps(reply).encode() + b"\n")


class Link:
    """This node's line to the coordinator: a direct call on node 0, one TCP request per question elsewhere."""

    def __init__(self, node: int, coordinator: Coordinator | None, address: tuple[str, int] | None) -> None:
        self.node = node
        self.coordinator = coordinator
        self.address = address

    def ask(self, op: str, **fields) -> Plan:
        """Raises OSError when node 0 cannot be reached."""
        request = {"op": op, "node": self.node, **fields}
        if self.coordinator is not None:
            return Plan(**self.coordinator.handle(request))
        with socket.create_connection(self.address, timeout=5) as conn:
            conn.sendall(json.dumps(request).encode() + b"\n")
            reply = conn.makefile("rb").readline()
        if not reply:
            raise ConnectionError("node 0 closed the connection")
        return Plan(**json.loads(reply))


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("", 0))
        return sock.getsockname()[1]


def plan_key(plan: Plan) -> dict:
    """What identifies an attempt across nodes."""
    return {"token": plan.token, "attempt": plan.attempt}


def rendezvous_args(plan: Plan, nnodes: int, options: SupervisorOptions, endpoint: tuple[str, int]) -> list[str]:
    """torchrun's static rendezvous for ``plan``: node 0's torchrun hosts the store on the plan's fresh port."""
    return [
        f"--nnodes={nnodes}",
        f"--node-rank={options.node_rank}",
        "--rdzv-backend=static",
        f"--master-addr={endpoint[0]}",
        f"--master-port={plan.port}",
        f"--rdzv-id=ftrain-{plan.token}-{plan.attempt}",
        f"--rdzv-conf=timeout={math.ceil(options.rdzv_timeout)}",
    ]
