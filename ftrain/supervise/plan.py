"""The plan every node of a run follows (which attempt runs now, and the exit code once the run has ended), and
torchrun's elastic rendezvous for an attempt of it.

Node 0's coordinator keeps the plan with c10d (``coordinator.py``), etcd with etcd-v2 (``etcd_plan.py``); both change
it by ``apply`` alone, so the nodes agree by the same rule whoever holds the record.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

from ftrain.identity import Identity
from ftrain.supervise.options import Nodes, SupervisorOptions

REGROUP_LAST_CALL = 1
"""Seconds a regroup after a node left waits for more than MIN nodes (torch's least; it polls once a second)."""


@dataclass
class Plan:
    """The attempt every node runs now; ``final`` is set once the run has ended."""

    generation: int
    """The generation its maker took from the storage's lease (``identity.py``): a plan made again (node 0's
    supervisor started again, a run started anew after its end) has a newer one."""
    attempt: int
    port: int | None
    """c10d: the port of node 0's rendezvous for this attempt (etcd-v2: None, etcd hosts the rendezvous)."""
    final: int | None = None
    left: int | None = None
    """The node whose leaving (its preemption, in an elastic etcd-v2 run) started this attempt; None after a failure."""
    nonce: str = ""
    """etcd: random, made with the plan, for torch's rendezvous ids (torch keeps a closed one for 2 hours; generations
    start over on another storage under the same ``--rdzv-id``)."""

    def identity(self, run_id: str, nnodes: int) -> Identity:
        """Who the workers of this attempt are: on several nodes with the attempt, whose commits are fenced
        (``fence.py``)."""
        return Identity(run_id, self.generation, self.attempt if nnodes > 1 else None)

    def token(self, pid: int) -> str:
        """What marks the processes of this attempt launched by supervisor ``pid`` (``attempt.py``)."""
        return f"{pid}-g{self.generation}-a{self.attempt}"


def plan_key(plan: Plan) -> dict:
    """What identifies an attempt across nodes."""
    return {"generation": plan.generation, "attempt": plan.attempt}


def apply(plan: Plan, request: dict, port: Callable[[], int | None]) -> Plan:
    """The plan after a node's ``request``: ``fail`` (``generation``, ``attempt``) moves every node to the next attempt
    (only the first report of the current attempt's failure counts) on a new rendezvous ``port()``; so does ``leave``
    (``node`` leaves the run, the others regroup without it); ``finish`` (``code``) ends the run with that exit code,
    once. Requests of another generation's plan change nothing."""
    ours = request.get("generation") == plan.generation and plan.final is None
    if request["op"] in ("fail", "leave") and ours and request.get("attempt") == plan.attempt:
        left = request.get("node") if request["op"] == "leave" else None
        return Plan(plan.generation, plan.attempt + 1, port(), left=left, nonce=plan.nonce)
    if request["op"] == "finish" and ours:
        return dataclasses.replace(plan, final=request["code"])
    return plan


def elastic_rendezvous(
    backend: str, plan: Plan, endpoint: str, run_id: str, nodes: Nodes, options: SupervisorOptions, **conf: object
) -> list[str]:
    """torchrun's elastic rendezvous arguments (c10d or etcd-v2) for ``plan``'s attempt: it starts once MIN nodes
    have joined and ``--rejoin-timeout`` has passed or MAX have joined (a node lost for good is thus left behind),
    gives up after ``--rdzv-timeout`` (``ftrain.torchrun`` then exits ``EXIT_RENDEZVOUS_TIMEOUT``), and, once
    training, lets its agents restart their workers with a larger world when a node joins late (the workers save on
    that SIGTERM: the world grows at a checkpoint boundary). A regroup after a node left on its own (``plan.left``,
    its preemption) waits no ``--rejoin-timeout``: every node that is not leaving launches at once, so the wait is
    ``REGROUP_LAST_CALL``, and one that still comes later joins as a late node does. A node that stops sending
    keep-alives drops out after torch's 15 s (3 missed of one per 5 s): every node's keep-alive goes through the
    store's host, so a stall of that host longer than the window (a loaded machine) would make every node look dead
    to the first to look again, and a node waiting to join would open a round alone and never be let in.
    ``conf``: the backend's own settings."""
    rejoin = REGROUP_LAST_CALL if plan.left is not None else max(REGROUP_LAST_CALL, math.ceil(options.rejoin_timeout))
    settings = {
        "join_timeout": math.ceil(options.rdzv_timeout),
        "last_call_timeout": rejoin,
        **conf,
    }
    return [
        f"--nnodes={nodes.least}:{nodes.count}",
        f"--rdzv-backend={backend}",
        f"--rdzv-endpoint={endpoint}",
        f"--rdzv-id={run_id}",
        "--rdzv-conf=" + ",".join(f"{key}={value}" for key, value in settings.items()),
    ]
