"""What a run will run, said once at its start: its ranks and hosts, how the update is shared between them (split by
model, or data-parallel and why), how the ranks meet, and the global batch. Rank 0 prints it as one line, and the
trainer writes it to ``<log_dir>/run.json``, next to ``config.yaml``, once the run has a step to start from and one
to train (a start refused as bad input, or one that finds the run at its last step, leaves the run's files as they
were)."""

from __future__ import annotations

import json
import socket
from collections.abc import Callable
from pathlib import Path

from ftrain.comm import group
from ftrain.comm.collectives import Comm
from ftrain.config import Config
from ftrain.files import replace_text
from ftrain.train.split import splits_update

RUN_FILE = "run.json"


def describe(config: Config, info: group.RankInfo, hosts: list[str], comm: Comm) -> dict:
    """The run as data: ``hosts``, every rank's host name in rank order; ``comm``, how the ranks meet."""
    world = info.world_size
    batch = {"ranks": world, "envs": config.env.num_envs, "steps": config.num_steps_per_env}
    batch["total"] = world * config.env.num_envs * config.num_steps_per_env
    return {
        "ranks": world,
        "hosts": {host: [rank for rank, name in enumerate(hosts) if name == host] for host in dict.fromkeys(hosts)},
        "update": _update(config, info),
        "transport": _transport(config, comm),
        "global_batch": batch,
    }


def _update(config: Config, info: group.RankInfo) -> dict:
    world = info.world_size
    if world == 1:
        return {"kind": "one rank"}
    if config.algorithm.class_name == "Distillation":
        return {"kind": "data-parallel", "why": "rsl-rl's distillation"}
    if splits_update(config, info):
        half = world // 2
        return {"kind": "split", "actor": list(range(half)), "critic": list(range(half, world))}
    why = "split_update=false" if not config.split_update else f"{world} ranks: a split needs an even number"
    return {"kind": "data-parallel", "why": why}


def _transport(config: Config, comm: Comm) -> str:
    if comm.size == 1 or comm.shared is not None:
        return comm.transport
    if not config.shared_memory_all_reduce:
        return "gloo (shared_memory_all_reduce=false)"
    if config.algorithm.class_name == "Distillation":
        return "gloo (rsl-rl's distillation)"
    return "gloo (the ranks' hosts could not be told apart)"


def summary(run: dict) -> str:
    """``describe``'s run in one line."""
    hosts = run["hosts"]
    where = ", ".join(f"{_ranks(ranks)} on {host}" for host, ranks in hosts.items())
    shared = update_words(run["update"])
    batch = run["global_batch"]
    ranks = "rank" if run["ranks"] == 1 else "ranks"
    return (
        f"{run['ranks']} {ranks} on {len(hosts)} host{'s' if len(hosts) > 1 else ''} ({where}) | update {shared} | "
        f"transport {run['transport']} | global batch {batch['total']:,} steps ({batch['ranks']} {ranks} x "
        f"{batch['envs']} envs x {batch['steps']} steps)"
    )


def update_words(update: dict) -> str:
    """How the update is shared between the ranks (``describe``'s ``update``), in words."""
    if update["kind"] == "split":
        team = len(update["actor"])
        within = f", data-parallel within each team of {team}" if team > 1 else ""
        return f"split: actor on {_ranks(update['actor'])}, critic on {_ranks(update['critic'])}{within}"
    if update["kind"] == "data-parallel":
        return f"data-parallel ({update['why']})"
    return "on one rank"


def announce(config: Config, info: group.RankInfo, comm: Comm, log: Callable[[str], None]) -> dict:
    """Every rank at the same point (it gathers the hosts' names): rank 0 logs the run's line."""
    run = describe(config, info, group.all_gather_object(socket.gethostname(), info), comm)
    if info.is_main:
        log(summary(run))
    return run


def write(log_dir: Path, run: dict) -> None:
    """``run`` (``describe``) as ``<log_dir>/run.json``."""
    replace_text(log_dir / RUN_FILE, json.dumps(run, indent=1) + "\n")


def _ranks(ranks: list[int]) -> str:
    """``rank 0``, ``ranks 0-3`` (consecutive), else ``ranks 0,2``."""
    if len(ranks) == 1:
        return f"rank {ranks[0]}"
    if ranks == list(range(ranks[0], ranks[-1] + 1)):
        return f"ranks {ranks[0]}-{ranks[-1]}"
    return f"ranks {','.join(map(str, ranks))}"
