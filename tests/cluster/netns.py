"""Simulated machines for the tests: Linux network namespaces, each with an address of its own on one bridge.

The bridge lives in a namespace of its own and every veth pair is made inside the namespaces (``ip -n``), so nothing
in the machine's own network changes; every name starts with this bed's prefix (the test process's pid and a random
part), so beds of parallel runs never meet. The hosts share the machine's files (a local storage directory is a
shared filesystem, as NFS would be), processes and hostname: only the network is theirs. ``stop()`` kills every
process left in the namespaces and deletes them, which takes the veth pairs and the bridge along."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import uuid
from pathlib import Path

SUBNET = "10.213.0"
"""The hosts' /24: host N has ``SUBNET.(N + 1)``."""
DEVICE = "eth0"
"""Each host's interface on the bridge."""
HUB = Path(__file__).with_name("delay_hub.py")


def missing() -> str | None:
    """Why network namespaces cannot be made here, or None."""
    if shutil.which("ip") is None:
        return "no ip command (apt-get install iproute2)"
    if os.geteuid() != 0:
        return "network namespaces (ip netns add) need root: run the tests as root"
    probe = f"ftrain-probe-{os.getpid()}-{uuid.uuid4().hex[:6]}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode:
        return f"ip netns add fails here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "delete", probe], check=True)
    return None


class Bed:
    """``hosts`` namespaces, host N at ``address(N)`` on its ``DEVICE``: one end of a veth pair whose other end,
    ``port(N)``, is on the bridge; or, with a delay, a TAP of ``delay_hub.py``, which runs in the bridge's namespace."""

    def __init__(self, hosts: int) -> None:
        self.prefix = f"ftrain-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self.bridge = f"{self.prefix}-bridge"
        self.hosts = [f"{self.prefix}-h{host}" for host in range(hosts)]
        self.made: list[str] = []
        self.hub: subprocess.Popen | None = None

    @staticmethod
    def address(host: int) -> str:
        return f"{SUBNET}.{host + 1}"

    @staticmethod
    def port(host: int) -> str:
        return f"port{host}"

    def launcher(self, host: int) -> list[str]:
        """What runs a command on ``host`` (``ip netns exec`` execs it: the process keeps its pid)."""
        return ["ip", "netns", "exec", self.hosts[host]]

    def start(self, delay_ms: int = 0) -> None:
        """Every namespace made and linked: by the kernel's bridge, or, with ``delay_ms``, by ``delay_hub.py``, which
        hands every frame on that many milliseconds late (each way: a round trip is twice as long)."""
        self._namespace(self.bridge)
        for name in self.hosts:
            self._namespace(name)
        if delay_ms:
            self._hub(delay_ms / 1000)
        else:
            _ip("-n", self.bridge, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.bridge, "link", "set", "br0", "up")
            for host, name in enumerate(self.hosts):
                port = self.port(host)
                _ip("-n", self.bridge, "link", "add", port, "type", "veth", "peer", "name", DEVICE, "netns", name)
                _ip("-n", self.bridge, "link", "set", port, "master", "br0", "up")
        for host, name in enumerate(self.hosts):
            _ip("-n", name, "addr", "add", f"{self.address(host)}/24", "dev", DEVICE)
            _ip("-n", name, "link", "set", DEVICE, "up")
            _ip("-n", name, "link", "set", "lo", "up")

    def _hub(self, delay: float) -> None:
        """``delay_hub.py`` in the bridge's namespace (``stop`` kills it with the rest), once its TAPs exist."""
        command = ["ip", "netns", "exec", self.bridge, sys.executable, str(HUB), str(delay), DEVICE, *self.hosts]
        self.hub = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if self.hub.stdout.readline().strip() != "ready":
            raise RuntimeError(f"delay_hub.py did not start: {self.hub.communicate()[1][-2000:]}")

    def stop(self) -> None:
        """Every process in the namespaces killed, every namespace deleted: also after a failure half-way."""
        for name in self.made:
            self._kill(name)
        if self.hub is not None:
            self.hub.communicate()
        for name in reversed(self.made):
            subprocess.run(["ip", "netns", "delete", name], capture_output=True)
        self.made.clear()

    def kill(self, host: int) -> list[int]:
        """SIGKILL every process of ``host`` at once, as a machine that lost power: their pids."""
        return self._kill(self.hosts[host])

    def link(self, host: int, up: bool) -> None:
        """``host``'s cable in or out: its bridge port up or down (its side then has no carrier); bridge only."""
        _ip("-n", self.bridge, "link", "set", self.port(host), "up" if up else "down")

    def pids(self, host: int) -> list[int]:
        return _pids(self.hosts[host])

    def _namespace(self, name: str) -> None:
        _ip("netns", "add", name)
        self.made.append(name)

    @staticmethod
    def _kill(name: str) -> list[int]:
        pids = _pids(name)
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        return pids


def _ip(*arguments: str) -> None:
    done = subprocess.run(["ip", *arguments], capture_output=True, text=True)
    if done.returncode:
        raise RuntimeError(f"ip {' '.join(arguments)}: {done.stderr.strip()}")


def _pids(name: str) -> list[int]:
    listed = subprocess.run(["ip", "netns", "pids", name], capture_output=True, text=True)
    return [int(pid) for pid in listed.stdout.split()]
