"""This node's line to what the nodes of a run agree on (``plan.py``), and torchrun's rendezvous, by backend.

One protocol, ``PlanLink``, with two keepers of the plan behind it: node 0's coordinator with c10d
(``coordinator.Link``), etcd with etcd-v2 (``etcd_plan.EtcdLink``). Both change the plan by ``plan.apply`` alone. The
supervisor holds a ``PlanLink`` and never asks which. May import ckpt, config and supervise's plan modules.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Protocol

from ftrain.ckpt.claim import storage_lease
from ftrain.ckpt.lease import Lease
from ftrain.config import Config
from ftrain.supervise.coordinator import Coordinator, Link, rendezvous_args
from ftrain.supervise.etcd_plan import EtcdLink, etcd_rendezvous_args
from ftrain.supervise.options import Backend, Nodes, SupervisorOptions
from ftrain.supervise.plan import Plan


class PlanLink(Protocol):
    """What a supervisor asks of the run's plan, wherever it is kept."""

    node: int
    """This node's number (c10d: its ``--node-rank``; etcd: taken from etcd when the link is made)."""
    peer: str
    """The plan's keeper, for messages: "node 0 at HOST:PORT" or "etcd at HOST:PORT"."""

    def begin(self, lease: Lease) -> None:
        """Once this node holds the storage's ``lease``: the plan made at its generation, or joined."""

    def ask(self, op: str, **fields) -> Plan:
        """The plan after this node's request (``plan.apply``; ``plan``: only read it). OSError: the keeper is not
        reached."""

    def settle(self, nnodes: int, timeout: float) -> None:
        """After the run's end was asked for: until every node can have learnt it, at most ``timeout`` seconds."""

    def close(self) -> None:
        """Stop serving the other nodes, if this link does."""


def connect(nodes: Nodes, options: SupervisorOptions, log: Callable[..., None]) -> PlanLink:
    """This node's link. c10d: node 0 (or one node alone) holds the coordinator and, of several, serves the others
    (``close`` the link). etcd-v2: waits up to ``--rdzv-timeout`` for etcd (``ConnectionError`` then). ``log``:
    records refused connections (an EventLog)."""
    if nodes.backend is Backend.ETCD:
        return EtcdLink(nodes, options.rdzv_timeout)
    multi = nodes.count > 1
    coordinator = Coordinator(multi, nodes.secret, log) if options.node_rank == 0 or not multi else None
    if multi and coordinator is not None:
        coordinator.serve(*nodes.endpoint)
    return Link(options.node_rank, coordinator, nodes.endpoint, nodes.secret)


def makes_plan(nodes: Nodes, options: SupervisorOptions) -> bool:
    """Whether this node makes the run's plan whenever it starts, at the next generation of the storage's lease:
    node 0 of several on c10d (on etcd, whichever node finds no current plan: ``EtcdLink.begin``; one node alone
    takes a new generation only as a new holder)."""
    return nodes.count > 1 and nodes.backend is not Backend.ETCD and options.node_rank == 0


def node_lease(config: Config, nodes: Nodes, options: SupervisorOptions, log: Callable[[str], None]) -> Lease:
    """The storage's lease for this node's supervisor, not taken yet: on several nodes, shared by their supervisors,
    all but the plan's maker following the plan's generation (``Lease``)."""
    follows = nodes.count > 1 and not makes_plan(nodes, options)
    return storage_lease(config, log, nodes.run_key, nodes.lease_endpoint, shared=nodes.count > 1, follows=follows)


def rendezvous(plan: Plan, nodes: Nodes, options: SupervisorOptions) -> list[str]:
    """torchrun's rendezvous arguments for ``plan``'s attempt: a fresh rendezvous every time. ``--local-addr``: the
    address this node gives the others, where its hostname resolves to none they reach (a host that shares its name
    with others, or whose name maps to 127.0.0.1: they would dial their own loopback)."""
    if nodes.count == 1:
        return ["--standalone"]
    local = [f"--local-addr={options.local_addr}"] if options.local_addr else []
    if nodes.backend is Backend.ETCD:
        return [*etcd_rendezvous_args(plan, nodes, options), *local]
    return [*rendezvous_args(plan, nodes, options), *local]


def worker_env(plan: Plan, nodes: Nodes, run_id: str) -> dict[str, str]:
    """What the workers of ``plan``'s attempt of run ``run_id`` add to their environment: their identity
    (``Plan.identity``: what their commits are checked against) and, with ``--local-addr``, ``GLOO_SOCKET_IFNAME``,
    the interface that holds it: else gloo binds to what the hostname resolves to and gives the other ranks that
    address (127.0.0.1 where the hostname maps to it: they dial their own loopback). A ``GLOO_SOCKET_IFNAME`` of the
    user's wins."""
    gloo = {"GLOO_SOCKET_IFNAME": os.environ.get("GLOO_SOCKET_IFNAME", nodes.interface)} if nodes.interface else {}
    return {**plan.identity(run_id, nodes.count).env(), **gloo}
