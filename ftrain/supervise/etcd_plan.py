"""Several nodes on etcd (``--rdzv-backend etcd-v2``): no node is special; what the supervisors agree on lives in etcd.

Plain torchrun on etcd restarts every node's workers in a new round after a failure, but it does not tell a hang,
bad input or an unreachable storage from a crash, does not count restarts that commit nothing, and reuses one
rendezvous across its restarts (docs/clusters.md has what was measured). So the supervisors keep their own restart
policy (``--max-restarts=0`` for torchrun, one fresh rendezvous per attempt, as with c10d) and keep in etcd only
what node 0's coordinator keeps for c10d: the plan (``plan.py``: the current attempt, the run's end, a node that
left), changed by compare-and-swap. Each node counts its own crash loop, and takes a number from etcd for its logs
and events (``node-N``): a node that starts again gets a new one.

Keys, under ``/ftrain/<--rdzv-id>``: ``plan`` (JSON) and ``nodes`` (the next node number). A supervisor that finds
no plan, or the plan of an ended run, makes a new one at the next generation of the storage's lease (``identity.py``):
running the same command again after a stop continues. Of two nodes that make one at once, the plan of the newer
generation stands (the other's workers could commit nothing), and the other node follows it.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import secrets
import sys
import time
from collections.abc import Callable
from typing import Any

from ftrain.ckpt.lease import Lease
from ftrain.errors import UserError
from ftrain.supervise.options import Nodes, SupervisorOptions
from ftrain.supervise.plan import Plan, apply, elastic_rendezvous

PREFIX = "/ftrain"
RETRY = 0.5
"""Seconds between two tries to reach etcd while the supervisor starts."""
MAKER_WAIT = 30.0
"""Seconds a node waits for the plan of the node that took the next generation before it (``EtcdLink.begin``)."""


def etcd_client(nodes: Nodes) -> Any:
    """A python-etcd client of ``nodes``' etcd, with the ``--rdzv-conf`` settings torch's etcd-v2 backend reads."""
    try:
        import etcd
    except ImportError:
        raise UserError("--rdzv-backend etcd-v2 needs python-etcd: pip install 'ftrain[etcd]'") from None
    conf = dict(nodes.conf)
    cert = conf.get("ssl_cert")
    if cert and conf.get("ssl_cert_key"):
        cert = (cert, conf["ssl_cert_key"])
    host, port = nodes.endpoint
    return etcd.Client(
        host,
        port,
        protocol=conf.get("protocol", "http"),
        cert=cert,
        ca_cert=conf.get("ca_cert"),
        read_timeout=int(conf.get("read_timeout", 10)),
    )


class EtcdLink:
    """This node's line to the run's plan in etcd (``link.PlanLink``): the same questions as ``coordinator.Link``,
    answered by etcd, which keeps the plan for every node (nothing to settle or close)."""

    def __init__(self, nodes: Nodes, timeout: float) -> None:
        """Takes a node number; waits up to ``timeout`` seconds for etcd (``ConnectionError`` then)."""
        self.client = etcd_client(nodes)  # first: a missing python-etcd is one line
        import etcd

        self._etcd = etcd
        self.peer = "etcd at {}:{}".format(*nodes.endpoint)
        self.key = f"{PREFIX}/{nodes.run_id}"
        self.timeout = timeout
        self.generation: int | None = None
        self.node = self._waiting(lambda: self._update("nodes", lambda count: (count or 0) + 1) - 1)

    def begin(self, lease: Lease) -> None:
        """Join the run's plan at the generation of the storage's ``lease`` that this node holds, or make it.

        A node that took that generation (a new holder: no process of it but this run's new ones) makes the plan at
        it where there is none at it yet. A node that joined it (other processes of the run hold it) waits
        ``MAKER_WAIT`` for the plan of the node that took it; where none comes (only old processes of the run hold
        it: a plan of theirs, ended or not, must not be joined), it takes the next generation (``Lease.advance``)
        and makes the plan at that, unless another node advanced first, whose plan it then waits for. A plan newer
        than the lease's generation is another storage's (the same ``--rdzv-id``): it is replaced. Waits for etcd as
        ``__init__`` does."""
        held, made = lease.generation, lease.took
        while (current := self._plan_at(held, lease)) is None:
            if made:
                self._waiting(lambda generation=held: self._update("plan", _made(generation, lease.current())))
                made = False
                continue
            deadline = time.monotonic() + MAKER_WAIT  # another node makes the plan at ``held``
            while time.monotonic() < deadline and self._plan_at(held, lease) is None:
                time.sleep(RETRY)
            if self._plan_at(held, lease) is None:
                held, made = lease.advance(held)
        self.generation = current.generation

    def _plan_at(self, generation: int, lease: Lease) -> Plan | None:
        """The plan in etcd if it is a live one of ``generation`` or newer, but not newer than the ``lease``'s."""
        plan = _parsed(self._waiting(lambda: self._update("plan", lambda value: value)))
        if plan is None or plan.final is not None or plan.generation < generation:
            return None
        return plan if plan.generation == generation or plan.generation <= lease.current() else None

    def ask(self, op: str, **fields) -> Plan:
        """The plan after this node's request (``plan``: only read it); ConnectionError when etcd cannot be reached."""
        request = {"op": op, "generation": self.generation, **fields}
        plan = Plan(**self._update("plan", lambda value: dataclasses.asdict(apply(_plan(value), request, _no_port))))
        self.generation = plan.generation
        return plan

    def settle(self, nnodes: int, timeout: float) -> None:
        """Every node reads the run's end from etcd: nobody to wait for."""

    def close(self) -> None:
        """Nothing held: each question is one request to etcd."""

    def _waiting(self, call: Callable[[], Any]) -> Any:
        """``call()``, tried again while etcd cannot be reached, up to ``timeout`` seconds (then ConnectionError)."""
        deadline = time.monotonic() + self.timeout
        for tries in itertools.count():
            try:
                return call()
            except ConnectionError as error:
                if time.monotonic() > deadline:
                    raise ConnectionError(f"{self.peer} not reached within {self.timeout:g} s ({error})") from None
                if not tries:
                    message = f"waiting up to {self.timeout:g} s for {self.peer} ({error})"
                    print(f"ftrain supervise: {message}", file=sys.stderr, flush=True)
                time.sleep(RETRY)

    def _update(self, name: str, change: Callable[[Any], Any]) -> Any:
        """``change`` the JSON value of ``name`` (None when absent) by compare-and-swap, retried until no other node
        wrote in between; the new value (as ``change`` returned it; None: there is none)."""
        key = f"{self.key}/{name}"
        while True:
            try:
                try:
                    current = self.client.read(key)
                    value, index = json.loads(current.value), current.modifiedIndex
                except self._etcd.EtcdKeyNotFound:
                    value, index = None, None
                new = change(value)
                encoded = json.dumps(new)
                if new is None:
                    return None
                if index is None:
                    self.client.write(key, encoded, prevExist=False)
                elif encoded != current.value:
                    self.client.write(key, encoded, prevIndex=index)
                return new
            except (self._etcd.EtcdCompareFailed, self._etcd.EtcdAlreadyExist):
                continue
            except self._etcd.EtcdException as error:
                raise ConnectionError(str(error) or type(error).__name__) from None


def _plan(value: dict | None) -> Plan:
    if (plan := _parsed(value)) is None:  # removed from etcd by hand while the run went on
        raise ConnectionError("the run's plan is gone from etcd")
    return plan


def _made(generation: int, newest: int) -> Callable[[dict | None], dict]:
    """The change to the plan in etcd of a node that made one at ``generation``: its plan, unless a live one of that
    generation or newer, up to the lease's ``newest``, is there already (another node made it)."""

    def change(value: dict | None) -> dict:
        plan = _parsed(value)
        if plan is None or plan.final is not None or not generation <= plan.generation <= newest:
            return dataclasses.asdict(Plan(generation, 0, None, nonce=secrets.token_hex(4)))
        return value

    return change


def _parsed(value: dict | None) -> Plan | None:
    """The plan of a record; None where there is none or it is not one (an older ftrain's record)."""
    try:
        return Plan(**value) if isinstance(value, dict) else None
    except TypeError:
        return None


def _no_port() -> None:
    return None  # etcd hosts the rendezvous


def etcd_rendezvous_args(plan: Plan, nodes: Nodes, options: SupervisorOptions) -> list[str]:
    """torchrun's etcd-v2 rendezvous for ``plan``'s attempt, always elastic (``--nnodes N``: N:N), with the
    ``--rdzv-conf`` connection settings. The round's rank 0 hosts the workers' store
    (``TORCH_DISABLE_SHARE_RDZV_TCP_STORE=1``, see ``attempt.attempt_env``): a node lost takes no other's store."""
    endpoint = "{}:{}".format(*nodes.endpoint)
    run_id = f"{nodes.run_id}-{plan.nonce}-g{plan.generation}-{plan.attempt}"  # torch keeps closed ones for 2 h
    return elastic_rendezvous("etcd-v2", plan, endpoint, run_id, nodes, options, **dict(nodes.conf))
