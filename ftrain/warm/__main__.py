"""``python -u -m ftrain.warm serve``: the warm pool, which ``ftrain supervise`` starts beside its attempts (see
``__init__``), on a socket the supervisor bound (a stand-in that comes early waits in its queue instead of starting
cold). It imports what it forks, then forks one child per stand-in. A forked child leaves the pool's loop with the
stand-in's request and runs its entry as the stand-in would have.

``python -m ftrain.warm torchrun ARGS``: the supervisor's stand-in for ``python -m ftrain.torchrun ARGS``."""

from __future__ import annotations

import atexit
import contextlib
import hmac
import importlib
import os
import select
import signal
import socket
import sys
import traceback
import weakref
from typing import NoReturn

from ftrain.lifeline import die_with_parent, die_with_supervisor
from ftrain.process import exit_fast, imports
from ftrain.proctitle import name_process
from ftrain.warm import ENTRIES, LISTENER_ENV, PEER, STREAMS, handover, receive_message, send_message

PRELOAD = ("ftrain.train.trainer", "ftrain.policy.robot", "gymnasium.envs.mujoco", "torch.distributed.run")
"""What ``ftrain train`` imports before its first iteration, MuJoCo's gymnasium environments included, and torchrun
(``ftrain.torchrun.agent`` imports it when it runs); the entries' modules come first."""
TORCHRUN = "torchrun"
"""The entry of torchrun's stand-in."""
REQUEST_TIMEOUT = 10.0
"""Seconds a stand-in has to send its request once connected: one that stalls must not stall the pool."""
STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)
"""What the pool ignores, and a fork gets back as the pool started with them (Python's at start: a SIGINT ignored since
the supervisor started, a script's background job, stays ignored in the workers too): a stop that reaches every process
of a run (SLURM signals every process of a job step) is for the workers, which save; the pool ends only with its
supervisor (``close``, or ``die_with_supervisor``), and its forks with it, so a pool that died of it would take the
workers down before their save."""


class Pool:
    def __init__(self, listener: socket.socket, secret: str, started_with: dict) -> None:
        self.listener = listener
        self.secret = secret
        self.started_with = started_with
        """Stop signal -> the handler the pool started with, which each fork gets back."""
        self.forks: dict[int, socket.socket | None] = {}
        """Forked process -> its stand-in's connection (None once the stand-in is gone)."""
        self.wakeup, wakeup_write = socket.socketpair()
        for end in (self.wakeup, wakeup_write):
            end.setblocking(False)
        self.sockets = [listener, self.wakeup, wakeup_write]
        signal.signal(signal.SIGCHLD, lambda number, frame: None)
        signal.set_wakeup_fd(wakeup_write.fileno())

    def serve(self) -> dict:
        """Fork until killed; returns only in a forked child, with its stand-in's request."""
        while True:
            connections = [connection for connection in self.forks.values() if connection is not None]
            for ready in select.select([self.listener, self.wakeup, *connections], [], [])[0]:
                if ready is self.listener:
                    request = self._accept()
                    if request is not None:
                        return request
                elif ready is self.wakeup:
                    with contextlib.suppress(BlockingIOError):
                        self.wakeup.recv(4096)
                    self._reap()
                else:
                    self._stand_in_gone(ready)

    def _accept(self) -> dict | None:
        """One stand-in's request: forked (its child gets the request back), or refused by closing the connection
        (another user, a wrong secret, a broken request, a failed fork): the stand-in then runs cold."""
        connection, _ = self.listener.accept()
        streams: list[int] = []
        try:
            connection.settimeout(REQUEST_TIMEOUT)
            _, uid, _ = PEER.unpack(connection.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, PEER.size))
            received = receive_message(connection, len(STREAMS)) if uid == os.getuid() else None
            request, streams = received or ({}, [])
            secret = str(request.get("secret") if isinstance(request, dict) else None).encode()
            if not hmac.compare_digest(secret, self.secret.encode()):
                raise ConnectionRefusedError("not a stand-in of this pool")
            pool = os.getpid()
            fork = os.fork()
        except (OSError, ValueError):
            for stream in streams:
                os.close(stream)
            connection.close()
            return None
        if fork == 0:
            self._become(request, streams, pool, connection)
            return request
        for stream in streams:
            os.close(stream)
        connection.settimeout(None)
        self.forks[fork] = connection  # the fork tells its stand-in its pid once it leads a process group of its own
        return None

    def _become(self, request: dict, streams: list[int], pool: int, connection: socket.socket) -> None:
        """In the forked child: the process the stand-in would have been, in its own session like torchrun's. Its
        stand-in learns its pid only then: a signal passed on to its process group reaches it, and is not ignored."""
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        for number, handler in self.started_with.items():  # as in a process just started
            signal.signal(number, handler)
        for end in [*self.sockets, *filter(None, self.forks.values())]:
            end.close()
        os.setsid()
        die_with_parent(pool)
        with contextlib.suppress(OSError):  # a stand-in gone meanwhile: the pool kills this process
            send_message(connection, {"pid": os.getpid()})
        connection.close()
        for target, stream in zip(STREAMS, streams, strict=True):
            if stream != target:
                os.dup2(stream, target)
                os.close(stream)
        os.chdir(request["cwd"])
        os.umask(request["umask"])
        os.environ.clear()
        os.environ.update(request["env"])
        sys.argv = request["sys_argv"]

    def _stand_in_gone(self, connection: socket.socket) -> None:
        """A stand-in's connection is readable only when it ends: its fork goes too (with its process group, as
        torchrun ends a worker's), stopped (hung) or not."""
        for fork, known in self.forks.items():
            if known is connection:
                for kill in (os.killpg, os.kill):  # the fork may not lead its group yet; unreaped, its pid is its own
                    with contextlib.suppress(ProcessLookupError):
                        kill(fork, signal.SIGKILL)
                self.forks[fork] = None
        connection.close()

    def _reap(self) -> None:
        """Tell each stand-in how its fork ended: its wait status."""
        while True:
            try:
                fork, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if fork == 0:
                return
            connection = self.forks.pop(fork, None)
            if connection is not None:
                with contextlib.suppress(OSError):
                    send_message(connection, {"status": status})
                connection.close()


def serve() -> NoReturn:
    die_with_supervisor()
    name_process(f"warm pool of supervisor {os.getppid()}")
    started_with = {number: signal.signal(number, signal.SIG_IGN) for number in STOP_SIGNALS}
    fd, _, secret = os.environ[LISTENER_ENV].partition(":")
    listener = socket.socket(fileno=int(fd))
    del os.environ[LISTENER_ENV]
    with imports():  # frozen before the first fork: the forks' collections do not copy the pages of what it imported
        entries = {name: getattr(importlib.import_module(module), func) for name, (module, func) in ENTRIES.items()}
        for name in PRELOAD:
            importlib.import_module(name)
    _forget_exit_functions()
    request = Pool(listener, secret, started_with).serve()
    try:
        code = entries[request["entry"]](request["argv"])
    except SystemExit as stop:
        code = stop.code
    except KeyboardInterrupt:  # a cold process dies of the SIGINT it did not handle: so does the fork
        traceback.print_exc()
        exit_fast(None, signal.SIGINT)
    except BaseException:
        traceback.print_exc()
        code = 1
    if code is not None and not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    exit_fast(code)


def _forget_exit_functions() -> None:
    """What the imports registered to run at exit belongs to the pool, not to its forks: e.g. wandb removes its
    temporary directories at exit, which the first fork to end would do for every fork after it."""
    atexit._clear()
    for finalizer in list(weakref.finalize._registry):
        finalizer.atexit = False
    weakref.finalize._registered_with_atexit = False


def stand_in_for_torchrun(argv: list[str]) -> int:
    """Like ``python -m ftrain.torchrun ARGV``, which it becomes where no pool answers."""
    die_with_supervisor()
    name_process("torchrun stand-in")
    code = handover(TORCHRUN, argv)
    if code is None:
        os.execv(sys.executable, [sys.executable, "-m", "ftrain.torchrun", *argv])
    return code


if __name__ == "__main__":
    if sys.argv[1:2] not in (["serve"], [TORCHRUN]):
        sys.exit("usage: python -m ftrain.warm serve | torchrun ARGS (started by ftrain supervise)")
    sys.exit(serve() if sys.argv[1] == "serve" else stand_in_for_torchrun(sys.argv[2:]))
