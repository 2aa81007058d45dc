"""Which network interface of this machine holds an address: ``--local-addr`` names the address the other nodes reach
this one at, and gloo, which the workers use, takes an interface (``GLOO_SOCKET_IFNAME``), not an address."""

from __future__ import annotations

import fcntl
import socket
import struct

from ftrain.errors import UserError

SIOCGIFADDR = 0x8915
"""Linux's ioctl for an interface's IPv4 address."""


def interface_of(address: str) -> str:
    """The name of the interface whose IPv4 address is ``address``; UserError where none is (a typo, or another
    machine's address)."""
    for _, name in socket.if_nameindex():
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            try:
                reply = fcntl.ioctl(probe.fileno(), SIOCGIFADDR, struct.pack("256s", name.encode()[:15]))
            except OSError:  # no IPv4 address
                continue
        if socket.inet_ntoa(reply[20:24]) == address:
            return name
    raise UserError(f"--local-addr={address!r} is no IPv4 address of this machine's interfaces: give this node's own")
