"""All-reduce, all-gather and broadcast through shared memory for ranks on one machine.

Why: a data-parallel update meets once per minibatch, and on one machine gloo's loopback round trips (a wake-up of
its I/O thread, then of the caller) dominate it; shared memory costs a copy and a byte per peer (docs/speed.md).

How: every rank copies its buffer into its own slot of a shared memory segment, tells each peer through a named pipe
(one byte, a blocking read: no busy waiting), waits for the peers' bytes, and sums the slots in rank order, so every
rank computes the bitwise same result. Two slot sets alternate, so a rank can write round k+1 while a slower peer
still reads round k, and no further. The segment and pipes are unlinked once every rank has opened them; their names
carry the creating process (``ftrain-<pid namespace>-<pid>-<start time>-...``), and the next creator on a host
removes those whose process is gone (``sweep``). A dead peer is end-of-file at once with two ranks, else a wait of
at most ``timeout_s``, like a gloo collective. May import: ``group``, ``ftrain.procfs``, torch.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import re
import select
import tempfile
import uuid

import torch
import torch.distributed as dist

from ftrain.comm.group import RankInfo, broadcast_object
from ftrain.procfs import start_time


class PeerLost(RuntimeError):
    """A peer died or stopped answering in the middle of an all-reduce."""


class SharedMemoryAllReduce:
    """Sum (or average) float32 buffers of up to ``capacity`` elements over all ranks of one machine, or over the
    ``ranks`` of ``group`` (global ranks, all on one machine).

    Construct it on every rank (of the group) at the same point: it uses the group once, to agree on names.
    """

    def __init__(
        self,
        info: RankInfo,
        capacity: int,
        timeout_s: float,
        group: dist.ProcessGroup | None = None,
        ranks: list[int] | None = None,
    ) -> None:
        ranks = list(range(info.world_size)) if ranks is None else ranks
        self.rank, self.world = ranks.index(info.rank), len(ranks)
        self.capacity = capacity
        self.timeout_ms = int(timeout_s * 1000)
        prefix = _new_prefix() if self.rank == 0 else None
        prefix = broadcast_object(prefix, info, group, src=ranks[0])
        segment, pipes = f"{prefix}.shm", [f"{prefix}-{rank}.fifo" for rank in range(self.world)]
        size = 2 * self.world * capacity * 4
        try:
            if self.rank == 0:
                fd = os.open(segment, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
                os.ftruncate(fd, size)
                os.close(fd)
                for pipe in pipes:
                    os.mkfifo(pipe, 0o600)
            dist.barrier(group=group)
            fd = os.open(segment, os.O_RDWR)
            self._map = mmap.mmap(fd, size)
            os.close(fd)
            self._slots = torch.frombuffer(self._map, dtype=torch.float32).view(2, self.world, capacity)
            # the reading end first, non-blocking, so opening never waits; then every peer's writing end, also
            # non-blocking: a peer that died in between makes the open fail (ENXIO) instead of waiting forever
            self._inbox = os.open(pipes[self.rank], os.O_RDONLY | os.O_NONBLOCK)
            dist.barrier(group=group)
            self._peers = [
                os.open(pipes[rank], os.O_WRONLY | os.O_NONBLOCK) for rank in range(self.world) if rank != self.rank
            ]
            dist.barrier(group=group)
        finally:  # once every rank has opened them (or failed), the names go: nothing is left behind
            if self.rank == 0:
                for path in (segment, *pipes):
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(path)
        self._poll = select.poll()
        self._poll.register(self._inbox, select.POLLIN)
        self._round = 0

    def all_reduce_(self, tensor: torch.Tensor) -> torch.Tensor:
        """In place: ``tensor`` (float32, contiguous, at most ``capacity`` elements) becomes the sum over ranks."""
        torch.sum(self._share(tensor), dim=0, out=tensor.view(-1))
        return tensor

    def all_gather(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` (float32, the same size on every rank), stacked in rank order: ``[world, n]``."""
        return self._share(tensor).clone()

    @property
    def broadcast_capacity(self) -> int:
        """The most elements :meth:`broadcast_` carries: one sender fills the round's slots of every rank."""
        return self.world * self.capacity

    def broadcast_(self, tensor: torch.Tensor, src: int) -> torch.Tensor:
        """In place: ``tensor`` (float32, contiguous, at most ``broadcast_capacity`` elements) becomes rank ``src``'s
        (its index among this reducer's ranks)."""
        area = self._slots[self._round % 2].view(-1)[: tensor.numel()]
        if self.rank == src:
            area.copy_(tensor.view(-1))
        self._share(tensor, publish=False)
        if self.rank != src:
            tensor.view(-1).copy_(area)
        return tensor

    def _share(self, tensor: torch.Tensor, publish: bool = True) -> torch.Tensor:
        """Publish ``tensor`` in this rank's slot (unless not ``publish``) and wait for every peer's: the round's
        slots, ``[world, n]``, valid until this rank's next round but one."""
        n = tensor.numel()
        slots = self._slots[self._round % 2, :, :n]
        self._round += 1
        if publish:
            slots[self.rank].copy_(tensor.view(-1))
        try:
            for peer in self._peers:
                os.write(peer, b"\x01")
        except BrokenPipeError:
            raise PeerLost("a peer rank exited during an all-reduce") from None
        self._await(self.world - 1)
        return slots

    def _await(self, count: int) -> None:
        while count:
            if not self._poll.poll(self.timeout_ms):
                raise PeerLost(f"no answer from the other ranks within {self.timeout_ms / 1000:.0f} s")
            try:
                got = os.read(self._inbox, count)
            except BlockingIOError:
                continue
            if not got:
                raise PeerLost("a peer rank exited during an all-reduce")
            count -= len(got)


def _owner_tag(pid: int) -> str | None:
    """``<pid namespace>-<pid>-<start time>``: what names a process for good on this host; None once it has ended
    (``start_time``: a zombie too)."""
    start = start_time(pid)
    return None if start is None else f"{_pid_namespace()}-{pid}-{start}"


def _new_prefix() -> str:
    """A fresh name for this process's segment and pipes, after a sweep of those whose creator is gone."""
    sweep()
    return os.path.join(_shared_dir(), f"{PREFIX}{_owner_tag(os.getpid())}-{uuid.uuid4().hex[:12]}")


def sweep() -> list[str]:
    """Remove the segments and pipes in this host's shared directory whose creator (of this pid namespace) is gone;
    the paths removed."""
    removed = []
    namespace = _pid_namespace()
    for entry in os.scandir(_shared_dir()):
        match = _NAME.match(entry.name)
        if match is None or match["ns"] != namespace:
            continue
        pid = int(match["pid"])
        if _owner_tag(pid) != f"{namespace}-{pid}-{match['start']}":
            with contextlib.suppress(OSError):  # gone meanwhile, or another user's (a sticky /dev/shm)
                os.unlink(entry.path)
                removed.append(entry.path)
    return removed


PREFIX = "ftrain-"
_NAME = re.compile(rf"^{PREFIX}(?P<ns>\d+)-(?P<pid>\d+)-(?P<start>\d+)-[0-9a-f]+(\.shm|-\d+\.fifo)$")


def _pid_namespace() -> str:
    """This process's pid namespace's number (pids of other namespaces mean nothing here); 0 where /proc hides it."""
    try:
        return os.readlink("/proc/self/ns/pid").partition("[")[2].rstrip("]") or "0"
    except OSError:
        return "0"


def _shared_dir() -> str:
    """RAM-backed /dev/shm where there is one, else the temp directory (the page cache serves it the same)."""
    return "/dev/shm" if os.path.isdir("/dev/shm") and os.access("/dev/shm", os.W_OK) else tempfile.gettempdir()
