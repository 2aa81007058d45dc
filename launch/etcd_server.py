"""A private etcd server on free ports (v2 API on, as torch's etcd-v2 rendezvous needs), on 127.0.0.1 or an address
of a network namespace, for the tests and benchmarks of runs without a special node."""

from __future__ import annotations

import contextlib
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from s3_outage import HOST, free_port, stop

MISSING = "no etcd binary: install Debian's etcd-server (launch/setup.sh does, as root)"
START_TIMEOUT = 30.0


@contextlib.contextmanager
def etcd_server(
    directory: Path, tls: dict[str, Path] | None = None, host: str = HOST, launcher: Sequence[str] = ()
) -> Iterator[str]:
    """etcd with its data and log (``etcd.log``) in ``directory`` while the block runs; yields its client address
    ``HOST:PORT``. ``tls``: PEM files ``server``, ``server_key`` and ``ca``: it then speaks https and answers only
    clients with a certificate of that CA. ``host``: the address it listens on; ``launcher``: what runs it and its
    readiness probe (``ip netns exec NAME``: etcd on a namespace's own address, which this namespace cannot reach).
    RuntimeError where there is no etcd binary (``MISSING``)."""
    binary = shutil.which("etcd")
    if binary is None:
        raise RuntimeError(MISSING)
    port, scheme = free_port(), "https" if tls else "http"
    client, peer = f"{scheme}://{host}:{port}", f"http://{host}:{free_port()}"
    command = [binary, "--enable-v2", "--data-dir", str(directory / "etcd"), "--listen-client-urls", client]
    command += ["--advertise-client-urls", client, "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer]
    command += ["--initial-cluster", f"default={peer}"]
    if tls:
        command += ["--cert-file", str(tls["server"]), "--key-file", str(tls["server_key"])]
        command += ["--trusted-ca-file", str(tls["ca"]), "--client-cert-auth"]
    log = directory / "etcd.log"
    with log.open("ab") as output:
        proc = subprocess.Popen([*launcher, *command], stdout=output, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not _listens(host, port, launcher):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"etcd did not start: {log.read_text()[-2000:]}")
            time.sleep(0.1)
        yield f"{host}:{port}"
    finally:
        stop(proc)


def _listens(host: str, port: int, launcher: Sequence[str]) -> bool:
    if launcher:
        probe = f"import socket; socket.create_connection(({host!r}, {port}), timeout=1)"
        return subprocess.run([*launcher, sys.executable, "-c", probe], capture_output=True).returncode == 0
    with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=1):
        return True
    return False
