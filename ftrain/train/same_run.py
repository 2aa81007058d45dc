"""One run on every rank: the ranks compare what they were started with before anything is built or taken.

Nodes are started apart (a command per host, SLURM's tasks, an elastic node joining late) and may be given another
file, other overrides or another ``--storage``. A rank with other training keys trains the run into something its
manifests do not record (they record rank 0's config), one with another length waits at the end for peers that have
stopped, and one with another storage writes shards that rank 0 never finds, so that no save commits. Compared: the
training keys (``config.training_part``), ``iterations`` and the storage as the run names it (``storage_identity``:
every node must name it alike). Every rank raises the same one-line UserError: the ranks that differ from rank 0 and
how. May import: comm.group, ckpt.changes, config, errors.
"""

from __future__ import annotations

from ftrain.ckpt.changes import config_change
from ftrain.comm import group
from ftrain.config import Config, storage_identity
from ftrain.errors import UserError


def check_same_run(config: Config, info: group.RankInfo) -> None:
    """UserError on every rank unless every rank was started with rank 0's training keys, length and storage."""
    if not info.distributed:
        return
    mine = {"config": config.public_dict(), "iterations": config.iterations}
    mine["storage"] = storage_identity(config.storage.url)
    first = group.broadcast_object(mine, info)
    differences = group.all_gather_object(_difference(first, mine), info)
    differing = [(rank, what) for rank, what in enumerate(differences) if what]
    if not differing:
        return
    rank, what = differing[0]
    others = f" (and {len(differing) - 1} more ranks)" if len(differing) > 1 else ""
    raise UserError(
        f"rank {rank}{others} was started with another run than rank 0: {what} (rank 0's -> rank {rank}'s): start "
        "every node with the same config, overrides and --storage"
    )


def _difference(first: dict, mine: dict) -> str | None:
    """How ``mine`` differs from rank 0's ``first``, in words; None: not at all."""
    parts = [config_change(first["config"], mine["config"], None, None)]
    parts += [f"{key} {first[key]} -> {mine[key]}" for key in ("iterations", "storage") if first[key] != mine[key]]
    return "; ".join(part for part in parts if part) or None
