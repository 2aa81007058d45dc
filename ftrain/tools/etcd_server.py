"""A private etcd server on free ports of 127.0.0.1 (v2 API on, as torch's etcd-v2 rendezvous needs), for the tests
and benchmarks of runs without a special node."""

from __future__ import annotations

import contextlib
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

from ftrain.tools.outage import HOST, free_port, stop

MISSING = "no etcd binary: install Debian's etcd-server (launch/setup.sh does, as root)"
START_TIMEOUT = 30.0


@contextlib.contextmanager
def etcd_server(directory: Path, tls: dict[str, Path] | None = None) -> Iterator[str]:
    """etcd with its data and log (``etcd.log``) in ``directory`` while the block runs; yields its client address
    ``HOST:PORT``. ``tls``: PEM files ``server``, ``server_key`` and ``ca``: it then speaks https and answers only
    clients with a certificate of that CA. RuntimeError where there is no etcd binary (``MISSING``)."""
    binary = shutil.which("etcd")
    if binary is None:
        raise RuntimeError(MISSING)
    port, scheme = free_port(), "https" if tls else "http"
    client, peer = f"{scheme}://{HOST}:{port}", f"http://{HOST}:{free_port()}"
    command = [binary, "--enable-v2", "--data-dir", str(directory / "etcd"), "--listen-client-urls", client]
    command += ["--advertise-client-urls", client, "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer]
    command += ["--initial-cluster", f"default={peer}"]
    if tls:
        command += ["--cert-file", str(tls["server"]), "--key-file", str(tls["server_key"])]
        command += ["--trusted-ca-file", str(tls["ca"]), "--client-cert-auth"]
    log = directory / "etcd.log"
    with log.open("ab") as output:
        proc = subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + START_TIMEOUT
        while not _listens(port):
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"etcd did not start: {log.read_text()[-2000:]}")
            time.sleep(0.1)
        yield f"{HOST}:{port}"
    finally:
        stop(proc)


def _listens(port: int) -> bool:
    with contextlib.suppress(OSError), socket.create_connection((HOST, port), timeout=1):
        return True
    return False
