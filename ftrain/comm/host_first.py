"""Collectives for a world that spans hosts, host first: a host's ranks meet in its shared memory, and only each host's
first rank crosses the network, in one gloo collective of the hosts' first ranks.

Why: gloo runs every collective as rounds between all ranks, each round across the network where ranks sit on two
hosts; host first, a meeting crosses once, whatever the ranks per host (docs/speed.md, "Across hosts").

Promises: an all-gather and a broadcast hand on every bit, so what the ranks sum from them (the iteration's small
float64 sums, summed in rank order after the gather) has the same bits on any layout of ranks on hosts. An
all-reduce sums within each host, in rank order, then across hosts: the same bits on every rank and at every run of
one layout, not the same as the one-host sum beyond rounding. May import: ``group``, ``shm_allreduce``, torch.
"""

from __future__ import annotations

import datetime
import math
import os
import socket

import torch
import torch.distributed as dist

from ftrain.comm.group import RankInfo, all_gather_object
from ftrain.comm.shm_allreduce import SharedMemoryAllReduce


def build_collectives(info: RankInfo, capacity: int, timeout_s: float, hosts: list[str] | None) -> Collectives | None:
    """The collectives of ranks that share memory: one host's, or host first across hosts (``hosts``, from
    :func:`hosts_of_ranks`); None (gloo for everything) at world size 1 or where the hosts are not known."""
    if not info.distributed or hosts is None:
        return None
    if len(set(hosts)) == 1:
        return SharedMemoryAllReduce(info, capacity, timeout_s)
    return HostFirst(info, hosts, capacity, timeout_s)


def hosts_of_ranks(info: RankInfo) -> list[str] | None:
    """Every rank's host, in rank order (torchrun's node rank, else the host name), or None where they disagree
    with torchrun's count of the ranks on this host (then no host is trusted to share memory). Every rank calls it
    at the same point."""
    host = os.environ.get("GROUP_RANK") or socket.gethostname()
    every = all_gather_object([host, int(os.environ.get("LOCAL_WORLD_SIZE", "0"))], info)
    hosts = [host for host, _ in every]
    return hosts if all(hosts.count(host) == local_world for host, local_world in every) else None


class HostFirst:
    """All-gather, broadcast and all-reduce of float32 buffers over all ranks, host first (the interface of
    :class:`SharedMemoryAllReduce`): a gather or a reduce of up to ``capacity`` elements per rank, a broadcast of up
    to ``broadcast_capacity``.

    Construct it on every rank at the same point: it makes a gloo group per host and one of the hosts' first ranks.
    """

    def __init__(self, info: RankInfo, hosts: list[str], capacity: int, timeout_s: float) -> None:
        names = list(dict.fromkeys(hosts))  # in the order of their first ranks
        self.members = [[rank for rank, host in enumerate(hosts) if host == name] for name in names]
        """Each host's ranks, in order; the first one crosses the network."""
        self.capacity = capacity
        self.broadcast_capacity = info.world_size * capacity
        self.world_size = info.world_size
        timeout = datetime.timedelta(seconds=timeout_s)
        local_groups = [
            dist.new_group(ranks, timeout=timeout, backend="gloo") if len(ranks) > 1 else None for ranks in self.members
        ]
        self._leaders = dist.new_group([ranks[0] for ranks in self.members], timeout=timeout, backend="gloo")
        self._host = names.index(hosts[info.rank])
        self._here = self.members[self._host]
        self._leads = self._here[0] == info.rank
        self._widest = max(map(len, self.members))
        # the local broadcast of a gather's result carries every rank's share: world x capacity over this host's slots
        local_capacity = math.ceil(self.broadcast_capacity / len(self._here))
        self._local = (
            SharedMemoryAllReduce(info, local_capacity, timeout_s, local_groups[self._host], self._here)
            if len(self._here) > 1
            else None
        )
        self._order = torch.tensor([rank for ranks in self.members for rank in ranks]).argsort()
        """Rows of the hosts' blocks, one after the other, in rank order."""

    def all_gather(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` (the same size on every rank), stacked in rank order: ``[world, n]``."""
        n = tensor.numel()
        mine = self._local.all_gather(tensor) if self._local is not None else tensor.view(1, -1)
        if self._leads:
            block = torch.zeros(self._widest, n)  # the hosts' blocks padded to one size, as gloo's all_gather needs
            block[: len(mine)] = mine
            blocks = [torch.empty_like(block) for _ in self.members]
            dist.all_gather(blocks, block, group=self._leaders)
            every = torch.cat([block[: len(ranks)] for block, ranks in zip(blocks, self.members, strict=True)])
            every = every[self._order]
        else:
            every = torch.empty(self.world_size, n)  # filled by this host's first rank
        if self._local is not None:
            self._local.broadcast_(every, 0)
        return every

    def broadcast_(self, tensor: torch.Tensor, src: int) -> torch.Tensor:
        """In place: ``tensor`` becomes global rank ``src``'s."""
        source = next(index for index, ranks in enumerate(self.members) if src in ranks)
        if self._host == source and self._local is not None:  # to this host's first rank, and the others here
            self._local.broadcast_(tensor, self._here.index(src))
        if self._leads:
            dist.broadcast(tensor, src=self.members[source][0], group=self._leaders)
        if self._host != source and self._local is not None:
            self._local.broadcast_(tensor, 0)
        return tensor

    def all_reduce_(self, tensor: torch.Tensor) -> torch.Tensor:
        """In place: ``tensor`` becomes the sum over ranks, within each host first (see the module's note on bits)."""
        if self._local is not None:
            self._local.all_reduce_(tensor)
        if self._leads:
            dist.all_reduce(tensor, group=self._leaders)
        if self._local is not None:
            self._local.broadcast_(tensor, 0)
        return tensor


Collectives = SharedMemoryAllReduce | HostFirst
"""Collectives through the ranks' shared memory: one host's, or host first across hosts."""
