"""Several nodes on etcd (``--rdzv-backend etcd-v2``): no node is special; what the supervisors agree on lives in etcd.

Measured with plain ``torchrun --rdzv-backend etcd-v2 --max-restarts 2`` on two agents (torch 2.13, etcd 3.4): when
one worker is killed, every node's agent restarts its workers in a new round (3 s to a new world of two), and once
an agent has used up its restarts every agent ends. So torchrun could number the attempts and end the run; it does
not tell a hang (it waits), bad input or an unreachable storage from a crash (it restarts them all alike, and burns
its restarts on an outage), nor does it count restarts that commit nothing, and its restarts reuse one rendezvous
whose first round's store a node keeps (see ``attempt.attempt_env``). So the supervisors keep their own restart
policy (``--max-restarts=0`` for torchrun, one fresh rendezvous per attempt, as with c10d) and keep in etcd only
what node 0's coordinator keeps for c10d: the plan (``plan.py``: the current attempt, the run's end, a node that
left), changed by compare-and-swap. The crash-loop count was never shared (each node counts its own). Each node
also takes a number from etcd for its logs and events (``node-N``): a node that starts again gets a new one.

Keys, under ``/ftrain/<--rdzv-id>``: ``plan`` (JSON) and ``nodes`` (the next node number). A supervisor that finds
the plan of an ended run starts a new one (a new token): running the same command again after a stop continues.
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

from ftrain.errors import UserError
from ftrain.supervise.options import Nodes, SupervisorOptions
from ftrain.supervise.plan import Plan, apply, elastic_rendezvous

PREFIX = "/ftrain"
RETRY = 0.5
"""Seconds between two tries to reach etcd while the supervisor starts."""


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
    """This node's line to the run's plan in etcd: the same questions as ``coordinator.Link``, answered by etcd."""

    def __init__(self, nodes: Nodes, timeout: float) -> None:
        """Takes a node number and, if the plan in etcd is of an ended run, starts a new plan; waits up to
        ``timeout`` seconds for etcd (``ConnectionError`` then)."""
        self.client = etcd_client(nodes)  # first: a missing python-etcd is one line
        import etcd

        self._etcd = etcd
        self.peer = "etcd at {}:{}".format(*nodes.endpoint)
        self.key = f"{PREFIX}/{nodes.run_id}"
        deadline = time.monotonic() + timeout
        for tries in itertools.count():
            try:
                self.node = self._update("nodes", lambda count: (count or 0) + 1) - 1
                self.token = self._update("plan", _fresh).token
                return
            except ConnectionError as error:
                if time.monotonic() > deadline:
                    raise ConnectionError(f"{self.peer} not reached within {timeout:g} s ({error})") from None
                if not tries:
                    message = f"waiting up to {timeout:g} s for {self.peer} ({error})"
                    print(f"ftrain supervise: {message}", file=sys.stderr, flush=True)
                time.sleep(RETRY)

    def ask(self, op: str, **fields) -> Plan:
        """The plan after this node's request (``plan``: only read it); ConnectionError when etcd cannot be reached."""
        request = {"op": op, "token": self.token, **fields}
        plan = self._update("plan", lambda value: apply(_plan(value), request, lambda: None))
        self.token = plan.token
        return plan

    def _update(self, name: str, change: Callable[[Any], Any]) -> Any:
        """``change`` the JSON value of ``name`` (None when absent) by compare-and-swap, retried until no other node
        wrote in between; the new value (as ``change`` returned it: a Plan or a number)."""
        key = f"{self.key}/{name}"
        while True:
            try:
                try:
                    current = self.client.read(key)
                    value, index = json.loads(current.value), current.modifiedIndex
                except self._etcd.EtcdKeyNotFound:
                    value, index = None, None
                new = change(value)
                encoded = json.dumps(dataclasses.asdict(new) if isinstance(new, Plan) else new)
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
    return Plan(**value) if value is not None else _new_plan()


def _new_plan() -> Plan:
    return Plan(secrets.token_hex(4), 0, None)


def _fresh(value: dict | None) -> Plan:
    """The plan a starting node joins: the current one, or a new one where there is none or the run has ended."""
    plan = _plan(value)
    return plan if plan.final is None else _new_plan()


def etcd_rendezvous_args(plan: Plan, nodes: Nodes, options: SupervisorOptions) -> list[str]:
    """torchrun's etcd-v2 rendezvous for ``plan``'s attempt, always elastic (``--nnodes N``: N:N), with the
    ``--rdzv-conf`` connection settings. The round's rank 0 hosts the workers' store
    (``TORCH_DISABLE_SHARE_RDZV_TCP_STORE=1``, see ``attempt.attempt_env``): a node lost takes no other's store."""
    endpoint = "{}:{}".format(*nodes.endpoint)
    run_id = f"{nodes.run_id}-{plan.token}-{plan.attempt}"
    return elastic_rendezvous("etcd-v2", plan, endpoint, run_id, nodes, options, **dict(nodes.conf))
