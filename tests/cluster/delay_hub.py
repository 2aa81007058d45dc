"""A hub that hands every Ethernet frame on ``DELAY`` seconds late: the links of ``netns.Bed`` with added latency.

``tc qdisc ... netem delay`` is the usual way, but kernels built without ``CONFIG_NET_SCH_NETEM`` (this project's
test machines among them: "Specified qdisc kind is unknown") have no netem, nor fq for a BPF-set departure time. So
each host gets a TAP device instead of a veth: this process creates it inside the host's namespace (``setns``, then
back), reads every frame a host sends and writes it to every other host's TAP once ``DELAY`` has passed, in order.
A frame thus arrives one ``DELAY`` after it left, each way, as with netem on every host's interface. The TAPs live
as long as this process: killing it unplugs every host.

Usage: ``python delay_hub.py DELAY DEVICE NAMESPACE...``; prints ``ready`` once every TAP exists."""

from __future__ import annotations

import contextlib
import ctypes
import fcntl
import heapq
import os
import selectors
import struct
import sys
import time

CLONE_NEWNET = 0x40000000
TUNSETIFF = 0x400454CA
IFF_TAP, IFF_NO_PI = 0x0002, 0x1000
FRAME = 65536


def open_tap(namespace: str, device: str) -> int:
    """A new TAP ``device`` in network namespace ``namespace``: its file descriptor (the device goes with it)."""
    libc = ctypes.CDLL(None, use_errno=True)
    home = os.open("/proc/self/ns/net", os.O_RDONLY)
    target = os.open(f"/run/netns/{namespace}", os.O_RDONLY)
    try:
        if libc.setns(target, CLONE_NEWNET):
            raise OSError(ctypes.get_errno(), f"setns into {namespace}")
        tap = os.open("/dev/net/tun", os.O_RDWR | os.O_NONBLOCK)
        fcntl.ioctl(tap, TUNSETIFF, struct.pack("16sH", device.encode(), IFF_TAP | IFF_NO_PI))
        return tap
    finally:
        if libc.setns(home, CLONE_NEWNET):
            raise OSError(ctypes.get_errno(), "setns back home")
        os.close(target)
        os.close(home)


def serve(delay: float, taps: list[int]) -> None:
    """Forever: every frame read from one TAP is written to all the others ``delay`` seconds later."""
    waiting: list[tuple[float, int, int, bytes]] = []  # (due, arrival number, source, frame)
    arrivals = 0
    selector = selectors.DefaultSelector()
    for tap in taps:
        selector.register(tap, selectors.EVENT_READ)
    while True:
        timeout = max(0.0, waiting[0][0] - time.monotonic()) if waiting else None
        for key, _ in selector.select(timeout):
            while True:
                try:
                    frame = os.read(key.fd, FRAME)
                except BlockingIOError:
                    break
                arrivals += 1
                heapq.heappush(waiting, (time.monotonic() + delay, arrivals, key.fd, frame))
        while waiting and waiting[0][0] <= time.monotonic():
            _, _, source, frame = heapq.heappop(waiting)
            for tap in taps:
                if tap != source:
                    with contextlib.suppress(OSError):  # a host whose interface is down drops it, as a cable would
                        os.write(tap, frame)


if __name__ == "__main__":
    seconds, name, *namespaces = sys.argv[1:]
    descriptors = [open_tap(namespace, name) for namespace in namespaces]
    print("ready", flush=True)
    serve(float(seconds), descriptors)
