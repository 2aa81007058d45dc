"""Storage outages on demand, for tests and benchmarks: moto's S3 API server behind a TCP proxy on 127.0.0.1.

Two kinds of outage, as the world has them: the port refuses (``refuse()``: the proxy stops listening, so a new
connection gets ECONNREFUSED, and resets the connections it carries) and the server hangs (``hang()``: SIGSTOP of
the server process, so requests are accepted by the kernel and never answered). ``restore()`` / ``unhang()`` end
them. Only the standard library: the proxy is threads and blocking sockets, two threads per connection.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

HOST = "127.0.0.1"


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as sock:
        sock.bind((HOST, 0))
        return sock.getsockname()[1]


def start_moto(port: int, log_path: str | Path) -> subprocess.Popen:
    """Start moto's S3 server on 127.0.0.1:``port`` and wait until it accepts connections."""
    log = open(log_path, "ab")  # noqa: SIM115 - the server writes to it for its whole life
    proc = subprocess.Popen([sys.executable, "-m", "moto.server", "-H", HOST, "-p", str(port)], stdout=log, stderr=log)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"moto server exited with {proc.returncode}: see {log_path}")
        with contextlib.suppress(OSError), socket.create_connection((HOST, port), timeout=0.5):
            return proc
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError(f"moto server did not listen on port {port} within 30 s: see {log_path}")


def stop(proc: subprocess.Popen) -> None:
    """End a server process (continued first, in case it was left stopped)."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(proc.pid, signal.SIGCONT)
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


class OutageProxy:
    """Forwards every connection to 127.0.0.1:``target_port`` until ``refuse()``; ``restore()`` listens again on
    the same port. Starts passing."""

    def __init__(self, target_port: int, port: int = 0) -> None:
        self.target = (HOST, target_port)
        self.port = port
        self._lock = threading.Lock()
        self._listener: socket.socket | None = None
        self._live: set[socket.socket] = set()
        self.restore()

    @property
    def endpoint_url(self) -> str:
        return f"http://{HOST}:{self.port}"

    @property
    def refusing(self) -> bool:
        return self._listener is None

    def restore(self) -> None:
        """Listen (again) on the proxy's port and forward."""
        with self._lock:
            if self._listener is not None:
                return
            listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # its old connections may be in TIME_WAIT
            listener.bind((HOST, self.port))
            listener.listen(256)
            self.port = listener.getsockname()[1]
            self._listener = listener
        threading.Thread(target=self._accept, args=(listener,), daemon=True, name="outage-accept").start()

    def refuse(self) -> None:
        """Stop listening (new connections: ECONNREFUSED) and reset every connection in flight."""
        with self._lock:
            listener, self._listener = self._listener, None
            live, self._live = self._live, set()
        if listener is not None:
            with contextlib.suppress(OSError):
                listener.shutdown(socket.SHUT_RDWR)  # wakes the thread blocked in accept(); close alone would not
            listener.close()
        for sock in live:
            _reset(sock)

    close = refuse

    def __enter__(self) -> OutageProxy:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            threading.Thread(target=self._connect, args=(client,), daemon=True, name="outage-conn").start()

    def _connect(self, client: socket.socket) -> None:
        try:
            upstream = socket.create_connection(self.target, timeout=10)
            upstream.settimeout(None)
        except OSError:
            _reset(client)  # the server is gone: the client sees a reset, as it would without the proxy
            return
        with self._lock:
            if self._listener is None:  # refused while connecting
                _reset(client)
                _reset(upstream)
                return
            self._live |= {client, upstream}
        for src, dst in ((client, upstream), (upstream, client)):
            threading.Thread(target=self._pump, args=(src, dst), daemon=True, name="outage-pump").start()

    def _pump(self, src: socket.socket, dst: socket.socket) -> None:
        """Copy one direction; at its end pass the half-close on, and close both once neither is live."""
        try:
            while data := src.recv(65536):
                dst.sendall(data)
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            _reset(src)
            _reset(dst)
        with self._lock:
            self._live.discard(src)
            gone = dst not in self._live
        if gone:
            src.close()
            dst.close()


def _reset(sock: socket.socket) -> None:
    """Abort a connection: the peer reads ECONNRESET (linger 0), and a thread blocked on it wakes up."""
    with contextlib.suppress(OSError):
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        sock.shutdown(socket.SHUT_RDWR)
    sock.close()


class S3Server:
    """A moto S3 server on its own port with an ``OutageProxy`` in front: ``endpoint_url`` goes through the proxy.
    Outages: ``refuse()`` / ``restore()`` (the port) and ``hang()`` / ``unhang()`` (the server process)."""

    def __init__(self, log_path: str | Path) -> None:
        self.server_port = free_port()
        self.proc = start_moto(self.server_port, log_path)
        self.proxy = OutageProxy(self.server_port)

    @property
    def endpoint_url(self) -> str:
        return self.proxy.endpoint_url

    @property
    def direct_url(self) -> str:
        """The server itself, past the proxy (e.g. to inspect a bucket while the proxy refuses)."""
        return f"http://{HOST}:{self.server_port}"

    def refuse(self) -> None:
        self.proxy.refuse()

    def restore(self) -> None:
        self.proxy.restore()

    def hang(self) -> None:
        """SIGSTOP the server: connections are still accepted (by the kernel), requests never answered."""
        os.kill(self.proc.pid, signal.SIGSTOP)

    def unhang(self) -> None:
        os.kill(self.proc.pid, signal.SIGCONT)

    def stop(self) -> None:
        self.proxy.close()
        stop(self.proc)

    def __enter__(self) -> S3Server:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
