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

from ftrain.ckpt.fence import GENERATION_ENV, epoch_of
from ftrain.ckpt.storage import Storage
from ftrain.config import StorageConfig
from ftrain.supervise.options import Nodes, SupervisorOptions

KEEP_ALIVE_INTERVAL = 1
KEEP_ALIVE_MISSES = 3
"""Elastic rendezvous: seconds between two keep-alives of a node's torchrun, and how many it may miss."""
REGROUP_LAST_CALL = 1
"""Seconds a regroup after a node left waits for more than MIN nodes (torch's least; it polls once a second)."""


@dataclass
class Plan:
    """The attempt every node runs now; ``final`` is set once the run has ended."""

    token: str
    """This run's token: a run started again after its end gets a new one."""
    attempt: int
    port: int | None
    """c10d: the port of node 0's rendezvous for this attempt (etcd-v2: None, etcd hosts the rendezvous)."""
    final: int | None = None
    left: int | None = None
    """The node whose leaving (its preemption, in an elastic etcd-v2 run) started this attempt; None after a failure."""


def plan_key(plan: Plan) -> dict:
    """What identifies an attempt across nodes."""
    return {"token": plan.token, "attempt": plan.attempt}


def apply(plan: Plan, request: dict, port: Callable[[], int | None]) -> Plan:
    """The plan after a node's ``request``: ``fail`` (``token``, ``attempt``) moves every node to the next attempt
    (only the first report of the current attempt's failure counts) on a new rendezvous ``port()``; so does ``leave``
    (``node`` leaves the run, the others regroup without it); ``finish`` (``code``) ends the run with that exit code,
    once. Requests of another run's token change nothing."""
    ours = request.get("token") == plan.token and plan.final is None
    if request["op"] in ("fail", "leave") and ours and request.get("attempt") == plan.attempt:
        return Plan(
            plan.token, plan.attempt + 1, port(), left=request.get("node") if request["op"] == "leave" else None
        )
    if request["op"] == "finish" and ours:
        return dataclasses.replace(plan, final=request["code"])
    return plan


_EPOCHS: dict[str, int] = {}
"""This supervisor's epochs by token (it runs on one storage)."""


def generation_env(plan: Plan, nnodes: int, storage: StorageConfig, numbers: bool) -> dict[str, str]:
    """The workers' generation on several nodes (``ftrain.ckpt.fence``: a node cut off from the others commits
    nothing once they have committed in a later attempt, or a newer token has its epoch); none on one node. The
    token's epoch comes from the ``storage``, once per token; ``numbers``: this node gives a token without one its
    epoch (see ``fence.epoch_of``)."""
    if nnodes == 1:
        return {}
    if plan.token not in _EPOCHS:  # a token's epoch never changes: the storage is asked once per token
        opened = Storage.open(storage.url, storage.options, check_bucket=False)
        _EPOCHS[plan.token] = epoch_of(opened, plan.token, numbers)
    return {GENERATION_ENV: f"{plan.token}:{_EPOCHS[plan.token]}:{plan.attempt}"}


def elastic_rendezvous(
    backend: str, plan: Plan, endpoint: str, run_id: str, nodes: Nodes, options: SupervisorOptions, **conf: object
) -> list[str]:
    """torchrun's elastic rendezvous arguments (c10d or etcd-v2) for ``plan``'s attempt: it starts once MIN nodes
    have joined and ``--rejoin-timeout`` has passed or MAX have joined (a node lost for good is thus left behind),
    gives up after ``--rdzv-timeout`` (``ftrain.dist.torchrun`` then exits ``EXIT_RENDEZVOUS_TIMEOUT``), and, once
    training, lets its agents restart their workers with a larger world when a node joins late (the workers save on
    that SIGTERM: the world grows at a checkpoint boundary). A regroup after a node left on its own (``plan.left``,
    its preemption) waits no ``--rejoin-timeout``: every node that is not leaving launches at once, so the wait is
    ``REGROUP_LAST_CALL``, and one that still comes later joins as a late node does. A node that stops sending
    keep-alives drops out after ``KEEP_ALIVE_INTERVAL`` x ``KEEP_ALIVE_MISSES`` seconds. ``conf``: the backend's own
    settings."""
    rejoin = REGROUP_LAST_CALL if plan.left is not None else max(REGROUP_LAST_CALL, math.ceil(options.rejoin_timeout))
    settings = {
        "join_timeout": math.ceil(options.rdzv_timeout),
        "last_call_timeout": rejoin,
        "keep_alive_interval": KEEP_ALIVE_INTERVAL,
        "keep_alive_max_attempt": KEEP_ALIVE_MISSES,
        **conf,
    }
    return [
        f"--nnodes={nodes.least}:{nodes.count}",
        f"--rdzv-backend={backend}",
        f"--rdzv-endpoint={endpoint}",
        f"--rdzv-id={run_id}",
        "--rdzv-conf=" + ",".join(f"{key}={value}" for key, value in settings.items()),
    ]
