"""Warm starts: a restart forks torchrun and its workers from a process that has imported torch, rsl-rl and MuJoCo.

Owns the pool (``python -m ftrain.warm serve``, one per supervisor, waiting on a Unix socket in the abstract
namespace named after it) and the stand-ins (``python -m ftrain.warm torchrun ...`` and each worker's ``python -m
ftrain train ...``). Promises:
- a process is started by the same command line as a cold one; its stand-in hands arguments, environment, working
  directory and standard streams to the pool (``handover``), which forks a child that runs with exactly those, so
  torchrun's agent, error files and exit codes stay torchrun's own;
- the stand-in is its parent's view of the child: it passes on signals and ends as the child ended;
- lifetimes are tied both ways: the pool ends with its supervisor (``lifeline``), a child with the pool
  (``PR_SET_PDEATHSIG``), and a stand-in's end SIGKILLs its child at once, a stopped (hung) one too;
- where the pool cannot be reached (``--workers cold``, plain ``torchrun -m ftrain train``, the pool ended, or its
  socket's name held by another process: a line) or closes before it forks, the stand-in runs the command cold;
- a stand-in talks only to its supervisor's socket (``SO_PEERCRED``), the pool only to processes of its user that
  know the secret of ``POOL_ENV``.
May import: errors, lifeline, proctitle, process. By name, the pool (``__main__.py``) forks the entries cli and
torchrun.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import struct
import sys

from ftrain.errors import raise_lost_stop
from ftrain.lifeline import SUPERVISOR_ENV, named_supervisor

POOL_ENV = "FTRAIN_WARM_POOL"
"""In the attempts' environment: the secret of this node's pool. A stand-in talks only to a socket its supervisor
listens on (``SO_PEERCRED`` names the process that called ``listen``: the socket's name can be guessed, and bound
first, by anyone on the machine) and proves itself with the secret (a process of the same user in another container
may share the network namespace, and so the name)."""
LISTENER_ENV = "FTRAIN_WARM_LISTENER"
"""In the pool's environment: the descriptor of the socket the supervisor bound for it, ``FD:SECRET``."""
START_TIMEOUT = 120.0
"""Seconds a stand-in waits for its fork (the pool may still be importing, at the first attempt) before it runs
cold."""
PEER = struct.Struct("iII")
"""``struct ucred``: pid, uid, gid of the process at the other end of a Unix socket."""
HEADER = struct.Struct("!I")
"""The length of a JSON message that follows."""
STREAMS = (0, 1, 2)
FORWARDED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)
"""What a stand-in passes on to its worker (SIGKILL and SIGSTOP cannot be caught: the pool sees the stand-in end)."""
ENTRIES = {"train": ("ftrain.cli", "main"), "torchrun": ("ftrain.torchrun.agent", "run")}
"""What a stand-in asks the pool to run: ``ftrain train ARGS`` (a worker), torchrun (``ftrain.torchrun``'s agent)."""


def address(supervisor: str) -> str:
    """The pool's socket for the supervisor named ``pid:start time`` (``FTRAIN_SUPERVISOR``)."""
    return f"\0ftrain-warm-{supervisor.replace(':', '-')}"


def send_message(connection: socket.socket, message: dict, fds: tuple[int, ...] = ()) -> None:
    data = json.dumps(message).encode()
    socket.send_fds(connection, [HEADER.pack(len(data))], list(fds))
    connection.sendall(data)


def receive_message(connection: socket.socket, max_fds: int = 0) -> tuple[dict, list[int]] | None:
    """The next message and the descriptors that came with it; None once the other end has closed. A message cut
    short, or not JSON, raises (OSError, ValueError), its descriptors closed."""
    header, fds = (
        socket.recv_fds(connection, HEADER.size, max_fds)[:2] if max_fds else (connection.recv(HEADER.size), [])
    )
    if not header:
        return None
    try:
        (length,) = HEADER.unpack(header + _receive(connection, HEADER.size - len(header)))
        return json.loads(_receive(connection, length)), fds
    except (OSError, ValueError):
        for fd in fds:
            os.close(fd)
        raise


def _receive(connection: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = connection.recv(size - len(data))
        if not chunk:
            raise ConnectionError("closed within a message")
        data += chunk
    return data


def handover(entry: str, argv: list[str]) -> int | None:
    """In a stand-in for ``entry`` (see ``ENTRIES``) under a supervisor whose pool answers: the pool's fork runs
    ``entry`` with ``argv``, this process waits for it and returns its exit code (or ends by its signal). None: no
    pool here, run cold."""
    named, secret = named_supervisor(), os.environ.get(POOL_ENV)
    if named is None or not secret:
        return None
    raise_lost_stop()  # before this process takes the signals over to pass them on: the pool's fork never got it
    _open_streams()
    connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    connection.settimeout(START_TIMEOUT)
    try:
        connection.connect(address(os.environ[SUPERVISOR_ENV]))
        server, uid, _ = PEER.unpack(connection.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, PEER.size))
    except OSError:
        connection.close()
        return None
    if (server, uid) != (named[0], os.getuid()):  # not bound by our supervisor: tell it nothing
        connection.close()
        return None
    pending: list[int] = []
    worker: list[int] = []

    def forward(number: int, frame: object) -> None:
        if not worker:
            pending.append(number)
            return
        with contextlib.suppress(ProcessLookupError):  # it has ended: its status is on the way
            os.killpg(worker[0], number)  # its group, as torchrun signals a worker's (the fork leads its own)

    taken = [number for number in FORWARDED if signal.getsignal(number) != signal.SIG_IGN]  # ignored: as a cold one
    previous = {number: signal.signal(number, forward) for number in taken}
    request = {"secret": secret, "entry": entry, "argv": argv, "sys_argv": sys.argv, "env": dict(os.environ)}
    try:
        send_message(connection, {**request, "cwd": os.getcwd(), "umask": _umask()}, STREAMS)
        started = receive_message(connection)
    except (OSError, ValueError):  # refused, or no fork within START_TIMEOUT
        started = None
    if started is None:  # the pool did not fork it: run cold, with the signals that came meanwhile
        connection.close()
        for number, handler in previous.items():
            signal.signal(number, handler)
        for number in pending:
            signal.raise_signal(number)
        return None
    connection.settimeout(None)
    worker.append(started[0]["pid"])
    for number in pending:
        forward(number, None)
    ended = receive_message(connection)
    for number in FORWARDED:  # its status is in: a late signal must not end this process otherwise
        signal.signal(number, signal.SIG_IGN)
    if ended is None:  # the pool died, and its workers with it
        print(f"ftrain: the warm pool ended while it ran {entry} for this process", file=sys.stderr)
        return 1
    status = ended[0]["status"]
    if os.WIFSIGNALED(status):  # end by the same signal: torchrun tells "killed by SIGKILL" from "exited 1"
        number = os.WTERMSIG(status)
        with contextlib.suppress(OSError, ValueError):  # SIGKILL and SIGSTOP have no handler to reset
            signal.signal(number, signal.SIG_DFL)
        os.kill(os.getpid(), number)
        return 128 + number  # a signal this process cannot die of
    return os.waitstatus_to_exitcode(status)


def _open_streams() -> None:
    """Standard streams that are closed get /dev/null: else the connection would take descriptor 0 and be handed to
    the fork as its stdin (and never close while it lives)."""
    for stream in STREAMS:
        try:
            os.fstat(stream)
        except OSError:
            os.dup2(os.open(os.devnull, os.O_RDWR), stream)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
