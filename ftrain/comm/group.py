"""Process group (gloo, with a timeout), rank info, per-rank seeding and the few collectives ftrain needs.

Objects travel between ranks as JSON, never as pickles: a peer sends data, not code.
"""

from __future__ import annotations

import datetime
import json
import os
import random
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist


@dataclass(frozen=True)
class RankInfo:
    rank: int
    world_size: int
    local_rank: int

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    def rsl_rl_cfg(self) -> dict | None:
        """rsl-rl's ``multi_gpu`` config: with it, its algorithms average gradients over the default group."""
        if not self.distributed:
            return None
        return {"global_rank": self.rank, "local_rank": self.local_rank, "world_size": self.world_size}


def init(timeout_s: float) -> RankInfo:
    """Join torchrun's process group over gloo; a plain ``python -m ftrain`` run is world size 1.

    The timeout bounds every collective, so a dead peer fails the survivors fast instead of hanging them.
    """
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group("gloo", timeout=datetime.timedelta(seconds=timeout_s))
    return RankInfo(rank, world_size, local_rank)


def shutdown() -> None:
    if dist.is_initialized():
        dist.destroy_process_group()


def new_group(timeout_s: float, info: RankInfo) -> dist.ProcessGroup | None:
    """A gloo group of all ranks besides the training one, for collectives of another thread (checkpoint saves);
    None at world size 1. Every rank must call it at the same point."""
    if not info.distributed:
        return None
    return dist.new_group(backend="gloo", timeout=datetime.timedelta(seconds=timeout_s))


def rank_seed(seed: int, rank: int, *at_step: int) -> int:
    """A well-mixed 31-bit seed per (seed, rank), or per (seed, rank, step) for a rank that joins a resumed run at
    ``step``: nearby seeds, ranks or steps never share streams."""
    return int(np.random.SeedSequence([seed, rank, *at_step]).generate_state(1)[0] >> 1)


def run_seed(seed: int, stream: str, *at_step: int) -> int:
    """A well-mixed 31-bit seed of the run's ``stream`` (the same on every rank), or of its restart at ``step``."""
    return int(np.random.SeedSequence([seed, *stream.encode(), *at_step], spawn_key=(1,)).generate_state(1)[0] >> 1)


def env_seed(seed: int, first_env: int, *at_step: int) -> int:
    """The seed of a rank's first environment (its ``i``-th gets this + ``i``, gymnasium's rule): the run's
    environment ``g`` is seeded alike whatever the number of ranks that share the environments."""
    return run_seed(seed, "envs", *at_step) + first_env


def seed_all(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def rng_state() -> dict:
    """torch, numpy and python RNG states as tensors and numbers (loadable with ``weights_only=True``)."""
    numpy_state = np.random.get_state(legacy=False)
    numpy_state["state"]["key"] = torch.from_numpy(numpy_state["state"]["key"].astype(np.int64))
    version, internal, gauss = random.getstate()
    python_state = [version, torch.from_numpy(np.array(internal, dtype=np.int64)), gauss]  # one tensor, not 625 ints
    return {"torch": torch.get_rng_state(), "numpy": numpy_state, "python": python_state}


def set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    numpy_state = dict(state["numpy"])
    numpy_state["state"] = {**numpy_state["state"], "key": numpy_state["state"]["key"].numpy().astype(np.uint32)}
    np.random.set_state(numpy_state)
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal.tolist()), gauss))


def broadcast_object(value: object, info: RankInfo, group: dist.ProcessGroup | None = None, src: int = 0) -> object:
    """Rank ``src``'s JSON-able ``value`` on every rank (of ``group``, which ``src`` is in)."""
    if not info.distributed:
        return value
    size = torch.zeros(1, dtype=torch.int64)
    data = _encode(value) if info.rank == src else torch.empty(0, dtype=torch.uint8)
    size[0] = data.numel()
    dist.broadcast(size, src=src, group=group)
    if info.rank != src:
        data = torch.empty(int(size[0]), dtype=torch.uint8)
    dist.broadcast(data, src=src, group=group)
    return _decode(data)


def all_gather_object(value: object, info: RankInfo, group: dist.ProcessGroup | None = None) -> list:
    """Every rank's JSON-able ``value``, in rank order."""
    if not info.distributed:
        return [value]
    data = _encode(value)
    sizes = [torch.zeros(1, dtype=torch.int64) for _ in range(info.world_size)]
    dist.all_gather(sizes, torch.tensor([data.numel()], dtype=torch.int64), group=group)
    longest = max(int(size[0]) for size in sizes)
    padded = torch.zeros(longest, dtype=torch.uint8)
    padded[: data.numel()] = data
    gathered = [torch.empty(longest, dtype=torch.uint8) for _ in range(info.world_size)]
    dist.all_gather(gathered, padded, group=group)
    return [_decode(chunk[: int(size[0])]) for chunk, size in zip(gathered, sizes, strict=True)]


def _encode(value: object) -> torch.Tensor:
    """As JSON: what peers send is data, never code (``broadcast_object_list`` would unpickle it)."""
    return torch.frombuffer(bytearray(json.dumps(value).encode()), dtype=torch.uint8)


def _decode(data: torch.Tensor) -> object:
    return json.loads(data.numpy().tobytes())
