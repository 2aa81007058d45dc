"""Warm starts: a restart forks torchrun and its workers from a process that has imported torch, rsl-rl and MuJoCo.

A cold restart spends most of its time importing: torchrun's agent imports torch (1.2 s), then each worker imports
torch, rsl-rl's tensordict (which imports torch's compiler), s3fs and gymnasium (2.5-3 s): most of the ~4.6 s from a
crash to the first iteration of the next attempt. ``ftrain supervise --workers warm`` (the default) starts one more
process on its node, the pool (``python -m ftrain.warm serve``: ``__main__.py``), which imports all of that once and
then waits on a Unix socket named after its supervisor.

Every process is still started as before, by the same command line, but as a stand-in: ``python -m ftrain.warm
torchrun ...`` for the supervisor's torchrun, ``python -m ftrain train ...`` for each worker torchrun starts (its
agent, its environment variables, error files and view of exit codes stay torchrun's own). The stand-in hands its
arguments, environment, working directory and standard streams to the pool (``handover``), which forks a child that
runs with exactly those. The stand-in stays as its parent's view of it: it passes on the signals it gets (SIGTERM:
save and stop) and ends as the child ended, with its exit code or by its signal.

Lifetimes are tied both ways, as for cold processes: the pool ends with its supervisor (``lifeline``), a forked child
ends with the pool (``PR_SET_PDEATHSIG``), and when a stand-in ends (stopped, or SIGKILLed by the supervisor, which
finds stand-ins by their attempt's token), the pool SIGKILLs its child at once, a stopped (hung) one too. Where the
pool cannot be reached (``--workers cold``, plain ``torchrun -m ftrain train``, or it ended) or closes the connection
before it forks, the stand-in simply runs the command itself, cold.

The socket is in Linux's abstract namespace (no file to leave behind) and the pool serves only processes of its own
user (``SO_PEERCRED``): whoever may run code as that user could run ``ftrain train`` anyway.

May import: lifeline, and by name in the pool (``__main__.py``) the entries it forks: cli, dist.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import struct
import sys

from ftrain.lifeline import SUPERVISOR_ENV

HEADER = struct.Struct("!I")
"""The length of a JSON message that follows."""
STREAMS = (0, 1, 2)
FORWARDED = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP, signal.SIGUSR1, signal.SIGUSR2)
"""What a stand-in passes on to its worker (SIGKILL and SIGSTOP cannot be caught: the pool sees the stand-in end)."""
ENTRIES = {"train": ("ftrain.cli", "main"), "torchrun": ("ftrain.dist.torchrun", "run")}
"""What a stand-in asks the pool to run: ``ftrain train ARGS`` (a worker), torchrun (``ftrain.dist.torchrun``)."""


def address(supervisor: str) -> str:
    """The pool's socket for the supervisor named ``pid:start time`` (``FTRAIN_SUPERVISOR``)."""
    return f"\0ftrain-warm-{supervisor.replace(':', '-')}"


def send_message(connection: socket.socket, message: dict, fds: tuple[int, ...] = ()) -> None:
    data = json.dumps(message).encode()
    socket.send_fds(connection, [HEADER.pack(len(data))], list(fds))
    connection.sendall(data)


def receive_message(connection: socket.socket, max_fds: int = 0) -> tuple[dict, list[int]] | None:
    """The next message and the file descriptors that came with it; None once the other end has closed."""
    header, fds = (
        socket.recv_fds(connection, HEADER.size, max_fds)[:2] if max_fds else (connection.recv(HEADER.size), [])
    )
    while header and len(header) < HEADER.size:
        header += connection.recv(HEADER.size - len(header))
    if len(header) < HEADER.size:
        return None
    (length,) = HEADER.unpack(header)
    data = b""
    while len(data) < length:
        chunk = connection.recv(length - len(data))
        if not chunk:
            return None
        data += chunk
    return json.loads(data), fds


def handover(entry: str, argv: list[str]) -> int | None:
    """In a stand-in for ``entry`` (see ``ENTRIES``) under a supervisor whose pool answers: the pool's fork runs
    ``entry`` with ``argv``, this process waits for it and returns its exit code (or ends by its signal). None: no
    pool here, run cold."""
    supervisor = os.environ.get(SUPERVISOR_ENV)
    if not supervisor:
        return None
    connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        connection.connect(address(supervisor))
    except OSError:
        connection.close()
        return None
    pending: list[int] = []
    worker: list[int] = []

    def forward(number: int, frame: object) -> None:
        if worker:
            os.kill(worker[0], number)
        else:
            pending.append(number)

    previous = {number: signal.signal(number, forward) for number in FORWARDED}
    request = {
        "entry": entry,
        "argv": argv,
        "sys_argv": sys.argv,
        "env": dict(os.environ),
        "cwd": os.getcwd(),
        "umask": _umask(),
    }
    send_message(connection, request, STREAMS)
    started = receive_message(connection)
    if started is None:  # the pool ended before it forked this worker (it could not import them): run cold
        for number, handler in previous.items():
            signal.signal(number, handler)
        connection.close()
        return None
    worker.append(started[0]["pid"])
    for number in pending:
        os.kill(worker[0], number)
    ended = receive_message(connection)
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


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
