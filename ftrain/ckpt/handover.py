"""How a save travels from a rank to its helper process: shared memory slots and socket messages.

Each message is a pickle between the two ends of one socket pair that the rank made (never a network peer): inline
in the packet when small, else in an anonymous shared memory file whose descriptor is sent. A save's tensors are
packed straight into a slot (one copy) and travel as offsets into it.
"""

from __future__ import annotations

import errno
import mmap
import os
import pickle
import socket
import struct

import torch

from ftrain.ckpt import packing

HEADER = struct.Struct("<QQ")
"""What goes over the socket with a shared memory file's descriptor: the message's offset and length in it."""
INLINE_LIMIT = 1 << 16
"""A message without a slot up to this size travels in the socket packet itself (one system call on each side)."""
ALIGNMENT = 64
"""Of everything placed in a :class:`Slot` (any dtype's alignment, and a cache line)."""


class Slot:
    """Shared memory that messages are written into: an anonymous memory file, mapped, reused save after save. The
    receiver maps the same file: tensors placed in it travel as ``(dtype, byte offset, numel)`` references, resolved
    by :func:`placed_tensors` into tensors over the shared memory itself."""

    def __init__(self, size: int = 1 << 20) -> None:
        self.fd = -1
        self.used = 0
        self._map(size)

    def clear(self, capacity: int) -> None:
        """Forget what was placed, and make room for ``capacity`` bytes."""
        self.used = 0
        if capacity > len(self.memory):
            self._map(2 * capacity)

    def allocate(self, dtype: torch.dtype, numel: int) -> torch.Tensor:
        """An empty 1-D tensor of ``numel`` x ``dtype`` placed in the slot (a :data:`ftrain.ckpt.packing.Allocate`).
        Fill it before the next placement: one that does not fit moves the slot's contents to a larger file."""
        start = self._reserve(numel * dtype.itemsize)
        return self.bytes[start : self.used].view(dtype)

    @staticmethod
    def reference(tensor: torch.Tensor) -> tuple[str, int, int]:
        """Where a tensor from :meth:`allocate` lies: ``(dtype, byte offset, numel)``."""
        return packing.dtype_name(tensor.dtype), tensor.storage_offset() * tensor.element_size(), tensor.numel()

    def append(self, data: bytes) -> int:
        """Copy ``data`` in; its offset."""
        start = self._reserve(len(data))
        self.memory[start : self.used] = data
        return start

    def _reserve(self, nbytes: int) -> int:
        start = -(-self.used // ALIGNMENT) * ALIGNMENT
        if start + nbytes > len(self.memory):
            self._map(2 * (start + nbytes))
        self.used = start + nbytes
        return start

    def _map(self, size: int) -> None:
        """Move to a new file of ``size`` bytes, what was placed at the same offsets."""
        fd = os.memfd_create("ftrain-save", os.MFD_CLOEXEC)
        try:
            os.ftruncate(fd, size)
            memory = mmap.mmap(fd, size)
        except BaseException:
            os.close(fd)
            raise
        placed = torch.frombuffer(memory, dtype=torch.uint8)
        if self.fd >= 0:
            placed[: self.used].copy_(self.bytes[: self.used])
        self.close()
        self.fd, self.memory, self.bytes = fd, memory, placed

    def close(self) -> None:
        """Give the file back (its mapping lives on while tensors over it do)."""
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def place(states: dict[str, dict], slot: Slot) -> dict[str, dict]:
    """Pack ``states`` (file name to state) into ``slot``: the packed states, each tensor a :meth:`Slot.reference`."""
    layouts = {name: packing.Layout(state) for name, state in states.items()}
    slot.clear(sum(layout.nbytes + layout.allocations * ALIGNMENT for layout in layouts.values()))
    files = {}
    for name, layout in layouts.items():
        packed = layout.fill(slot.allocate)
        placed = {dtype: slot.reference(flat) for dtype, flat in packed["tensors"].items()}
        files[name] = packed | {"index": slot.reference(packed["index"]), "tensors": placed}
    return files


def send(sock: socket.socket, message: object, slot: Slot | None = None) -> None:
    """Send ``message``: pickled into ``slot`` after the tensors placed there, with the slot's descriptor; without a
    slot, a small message (an outcome, the start-up) goes inline in the packet, a larger one in a fresh slot.
    Sending never waits for the receiver: the socket's buffer, a few hundred kB, holds a few inline messages."""
    data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
    if slot is None and len(data) <= INLINE_LIMIT:
        try:
            sock.sendmsg([data])
            return
        except OSError as error:  # a socket buffer smaller than the limit: the shared memory way then
            if error.errno != errno.EMSGSIZE:
                raise
    own = slot is None
    slot = Slot(len(data)) if own else slot
    try:
        offset = slot.append(data)
        socket.send_fds(sock, [HEADER.pack(offset, len(data))], [slot.fd])
    finally:
        if own:
            slot.close()


def receive(sock: socket.socket) -> tuple[object, mmap.mmap | None] | None:
    """The next message and the shared memory it came in (None if inline), or None once the other side has closed
    the socket."""
    data, fds, flags, _ = socket.recv_fds(sock, INLINE_LIMIT, 1)
    if flags & (socket.MSG_TRUNC | socket.MSG_CTRUNC):
        for fd in fds:
            os.close(fd)
        raise OSError(errno.EMSGSIZE, "a message or its file descriptor did not arrive whole")
    if not data:
        return None
    if not fds:
        return pickle.loads(data), None
    try:
        memory = mmap.mmap(fds[0], os.fstat(fds[0]).st_size)
    finally:
        os.close(fds[0])
    offset, length = HEADER.unpack(data)
    return pickle.loads(memory[offset : offset + length]), memory


def placed_tensors(packed: dict, memory: mmap.mmap) -> dict:
    """A packed state whose tensors are :meth:`Slot.reference` s into ``memory``, with tensors over ``memory``."""
    tensors = {name: _placed(reference, memory) for name, reference in packed["tensors"].items()}
    return packed | {"index": _placed(packed["index"], memory), "tensors": tensors}


def _placed(reference: tuple[str, int, int], memory: mmap.mmap) -> torch.Tensor:
    name, offset, numel = reference
    dtype = getattr(torch, name)
    if numel == 0:  # frombuffer refuses an empty range
        return torch.empty(0, dtype=dtype)
    return torch.frombuffer(memory, dtype=dtype, count=numel, offset=offset)
