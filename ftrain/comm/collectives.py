"""How the ranks meet: every collective of the training loop goes through one ``Comm``, which picks its transport.

Owns the one decision between the ranks' shared memory (one host's, ``shm_allreduce``; or host first across hosts,
``host_first``) and gloo. The buffers are sized once, from the world size and the largest tensor the caller says it
will send (``Traffic``); a collective that fits goes through shared memory, one that does not goes through gloo, is
named once in the log with its size and the buffer's, and is counted in ``fallbacks`` (``metrics.csv``: a run that is
slower than it should be says why). Promises: a gather and a broadcast hand on every bit; ``all_reduce_sum_`` gives
every rank the same bits. Every rank of the group calls every method at the same point.

May import: ``ftrain.comm``'s other modules, torch and the standard library.
"""

from __future__ import annotations

import datetime
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.distributed as dist

from ftrain.comm.group import RankInfo
from ftrain.comm.host_first import Collectives, HostFirst, build_collectives, hosts_of_ranks
from ftrain.comm.shm_allreduce import SharedMemoryAllReduce


@dataclass(frozen=True)
class Traffic:
    """The largest tensors a group's collectives will carry, in float32 elements: what the buffers are sized for."""

    per_rank: int
    """The largest tensor one rank contributes to an all-reduce or an all-gather."""
    broadcast: int = 0
    """The largest tensor one rank broadcasts."""

    def capacity(self, ranks: int) -> int:
        """Elements per rank's slot: a broadcast fills the slots of every rank of the group."""
        return max(self.per_rank, math.ceil(self.broadcast / ranks), 1)


class Comm:
    """The collectives of a group of ranks (all of them, or a team): shared memory where they share it and a tensor
    fits, else gloo (said once per size, and counted)."""

    def __init__(
        self,
        info: RankInfo,
        ranks: list[int],
        group: dist.ProcessGroup | None,
        shared: Collectives | None,
        say: Callable[[str], None],
        hosts: list[str] | None = None,
        counters: dict[str, int] | None = None,
    ) -> None:
        self.info = info
        self.ranks = ranks
        self.group = group
        self.shared = shared
        """The ranks' shared memory (None: gloo for everything)."""
        self.hosts = hosts
        """Every rank's host, where shared memory was asked for and the hosts agree."""
        self._say = say
        self._counters = counters if counters is not None else {"fallbacks": 0, "sent": 0, "taken": 0}
        """Fallbacks and bytes sent by this rank, of this comm and of those made from it (``team``), in one count."""
        self._said: set[tuple[str, int]] = set()

    @classmethod
    def build(
        cls, info: RankInfo, traffic: Traffic, timeout_s: float, shared_memory: bool, say: Callable[[str], None]
    ) -> Comm:
        """Every rank at the same point: the comm of all ranks. ``shared_memory``: use it where ranks share a host
        (the config's ``shared_memory_all_reduce``); ``say``: where a fallback is said (every rank calls it; the
        first rank of the group prints)."""
        hosts = hosts_of_ranks(info) if shared_memory and info.distributed else None
        shared = build_collectives(info, traffic.capacity(info.world_size), timeout_s, hosts)
        return cls(info, list(range(info.world_size)), None, shared, say, hosts)

    def team(self, teams: list[list[int]], traffic: Traffic, timeout_s: float) -> Comm:
        """Every rank at the same point, with the same ``teams`` (global ranks that meet among themselves): the comm
        of this rank's team, with a gloo group of its own and its shared memory where its ranks share a host. Its
        fallbacks count in this comm's."""
        timeout = datetime.timedelta(seconds=timeout_s)
        groups = [dist.new_group(ranks, backend="gloo", timeout=timeout) if len(ranks) > 1 else None for ranks in teams]
        number = next(index for index, ranks in enumerate(teams) if self.info.rank in ranks)
        ranks, group = teams[number], groups[number]
        shared = None
        if len(ranks) > 1 and self.hosts is not None and len({self.hosts[rank] for rank in ranks}) == 1:
            shared = SharedMemoryAllReduce(self.info, traffic.capacity(len(ranks)), timeout_s, group, ranks)
        return Comm(self.info, ranks, group, shared, self._say, self.hosts, self._counters)

    @property
    def size(self) -> int:
        return len(self.ranks)

    @property
    def fallbacks(self) -> int:
        """Collectives that went through gloo because they did not fit the shared buffer, since the start."""
        return self._counters["fallbacks"]

    def take_sent(self) -> int:
        """The bytes this rank has put into collectives since the last call (a broadcast's: its source's)."""
        sent = self._counters["sent"] - self._counters["taken"]
        self._counters["taken"] = self._counters["sent"]
        return sent

    @property
    def transport(self) -> str:
        """How these ranks meet, in words."""
        if self.size == 1:
            return "none (one process)"
        if isinstance(self.shared, HostFirst):
            return "shared memory within hosts, gloo between them"
        return "shared memory (one host)" if self.shared is not None else "gloo"

    def all_reduce_sum_(self, tensor: torch.Tensor) -> torch.Tensor:
        """In place: ``tensor`` (float32, contiguous) becomes the sum over the group's ranks."""
        if self.size == 1:
            return tensor
        self._counters["sent"] += tensor.numel() * tensor.element_size()
        if self._fits("all-reduce", tensor.numel(), self._capacity):
            return self.shared.all_reduce_(tensor)
        dist.all_reduce(tensor, group=self.group)
        return tensor

    def all_gather(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` (float32, the same size on each), stacked in the group's order: ``[ranks, n]``."""
        if self.size == 1:
            return tensor.view(1, -1)
        self._counters["sent"] += tensor.numel() * tensor.element_size()
        if self._fits("all-gather", tensor.numel(), self._capacity):
            return self.shared.all_gather(tensor)
        every = [torch.empty_like(tensor) for _ in self.ranks]
        dist.all_gather(every, tensor, group=self.group)
        return torch.stack(every)

    def broadcast_(self, tensor: torch.Tensor, src: int) -> torch.Tensor:
        """In place: ``tensor`` becomes global rank ``src``'s."""
        if self.size == 1:
            return tensor
        if self.info.rank == src:
            self._counters["sent"] += tensor.numel() * tensor.element_size()
        if self._fits("broadcast", tensor.numel(), self.shared.broadcast_capacity if self.shared else 0):
            if isinstance(self.shared, HostFirst):
                return self.shared.broadcast_(tensor, src)
            return self.shared.broadcast_(tensor, self.ranks.index(src))
        dist.broadcast(tensor, src=src, group=self.group)
        return tensor

    def gather_values(self, values: list[float]) -> torch.Tensor:
        """Every rank's few numbers, ``[ranks, n]`` float64 in rank order (counts stay exact): as float32 bits."""
        tensor = torch.tensor(values, dtype=torch.float64)
        return self.all_gather(tensor.view(torch.float32)).view(torch.float64)

    def sum_values(self, values: list[float]) -> list[float]:
        """A few numbers summed over the ranks (float64), gathered and summed in rank order: the same bits on every
        rank, whatever the ranks' layout on hosts and the transport."""
        return self.gather_values(values).sum(dim=0).tolist()

    @property
    def _capacity(self) -> int:
        return self.shared.capacity if self.shared is not None else 0

    def _fits(self, what: str, size: int, capacity: int) -> bool:
        """Whether a collective of ``size`` elements goes through shared memory; a fallback is counted, and said once
        per kind and size."""
        if self.shared is None:
            return False
        if size <= capacity:
            return True
        self._counters["fallbacks"] += 1
        if (what, size) not in self._said:
            self._said.add((what, size))
            if self.info.rank == self.ranks[0]:
                self._say(
                    f"a collective ({what}) of {size:,} floats per rank does not fit the ranks' shared memory "
                    f"({capacity:,}): through gloo, slower (counted in metrics.csv as comm_fallbacks)"
                )
        return False
