"""``python -u -m ftrain.warm serve``: the warm pool, which ``ftrain supervise`` starts beside its attempts (see
``__init__``). It binds its socket at once (a stand-in that comes early waits in the queue instead of starting
cold), imports what it forks, then forks one child per stand-in. A forked child leaves the pool's loop with the
stand-in's request and runs its entry as the stand-in would have.

``python -m ftrain.warm torchrun ARGS``: the supervisor's stand-in for ``python -m ftrain.dist.torchrun ARGS``."""

from __future__ import annotations

import atexit
import contextlib
import importlib
import os
import select
import signal
import socket
import struct
import sys
import threading
import traceback
from typing import NoReturn

from ftrain.lifeline import SUPERVISOR_ENV, die_with_parent, die_with_supervisor
from ftrain.warm import ENTRIES, STREAMS, address, handover, receive_message, send_message

PRELOAD = ("ftrain.train.trainer", "ftrain.policy.robot", "gymnasium.envs.mujoco")
"""What ``ftrain train`` imports before its first iteration, MuJoCo's gymnasium environments included (the entries'
modules come first)."""
TORCHRUN = "torchrun"
PEER = struct.Struct("3i")
"""``struct ucred``: pid, uid, gid of a connected process."""


class Pool:
    def __init__(self, listener: socket.socket) -> None:
        self.listener = listener
        self.workers: dict[int, socket.socket | None] = {}
        """Forked worker -> its stand-in's connection (None once the stand-in is gone)."""
        self.wakeup, wakeup_write = socket.socketpair()
        for end in (self.wakeup, wakeup_write):
            end.setblocking(False)
        self.sockets = [listener, self.wakeup, wakeup_write]
        signal.signal(signal.SIGCHLD, lambda number, frame: None)
        signal.set_wakeup_fd(wakeup_write.fileno())

    def serve(self) -> dict:
        """Fork workers until killed; returns only in a forked worker, with its stand-in's request."""
        while True:
            connections = [connection for connection in self.workers.values() if connection is not None]
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
        connection, _ = self.listener.accept()
        _, uid, _ = PEER.unpack(connection.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, PEER.size))
        received = receive_message(connection, len(STREAMS)) if uid == os.getuid() else None
        if received is None:
            connection.close()
            return None
        request, streams = received
        pool = os.getpid()
        worker = os.fork()
        if worker == 0:
            self._become(request, streams, pool, connection)
            return request
        for stream in streams:
            os.close(stream)
        self.workers[worker] = connection
        with contextlib.suppress(OSError):
            send_message(connection, {"pid": worker})
        return None

    def _become(self, request: dict, streams: list[int], pool: int, connection: socket.socket) -> None:
        """In the forked child: the worker the stand-in would have been, in its own session like torchrun's."""
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        for end in [*self.sockets, connection, *filter(None, self.workers.values())]:
            end.close()
        os.setsid()
        die_with_parent(pool)
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
        """A stand-in's connection is readable only when it ends: its worker goes too, stopped (hung) or not."""
        for worker, known in self.workers.items():
            if known is connection:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(worker, signal.SIGKILL)
                self.workers[worker] = None
        connection.close()

    def _reap(self) -> None:
        """Tell each stand-in how its worker ended: its wait status."""
        while True:
            try:
                worker, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                return
            if worker == 0:
                return
            connection = self.workers.pop(worker, None)
            if connection is not None:
                with contextlib.suppress(OSError):
                    send_message(connection, {"status": status})
                connection.close()


def serve() -> NoReturn:
    die_with_supervisor()
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(address(os.environ[SUPERVISOR_ENV]))
    listener.listen(64)
    entries = {name: getattr(importlib.import_module(module), function) for name, (module, function) in ENTRIES.items()}
    for name in PRELOAD:
        importlib.import_module(name)
    request = Pool(listener).serve()
    try:
        code = entries[request["entry"]](request["argv"])
    except SystemExit as stop:
        code = stop.code if isinstance(stop.code, int) else (print(stop.code, file=sys.stderr) or 1)
    except BaseException:
        traceback.print_exc()
        code = 1
    exit_fast(code)


def exit_fast(code: int) -> NoReturn:
    """End a forked child as Python's multiprocessing ends its own: after the threads that keep a process alive, the
    atexit functions and a flush, but without tearing the interpreter down, which writes to every object the pool
    imported and so copies all of its memory (1.1-1.5 s measured, against 0.06 s)."""
    for thread in threading.enumerate():
        if thread is not threading.main_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(code)


def stand_in_for_torchrun(argv: list[str]) -> int:
    """Like ``python -m ftrain.dist.torchrun ARGV``, which it becomes where no pool answers."""
    die_with_supervisor()
    code = handover(TORCHRUN, argv)
    if code is None:
        module = ENTRIES[TORCHRUN][0]
        os.execv(sys.executable, [sys.executable, "-m", module, *argv])
    return code


if __name__ == "__main__":
    if sys.argv[1:2] not in (["serve"], [TORCHRUN]):
        sys.exit("usage: python -m ftrain.warm serve | torchrun ARGS (started by ftrain supervise)")
    sys.exit(serve() if sys.argv[1] == "serve" else stand_in_for_torchrun(sys.argv[2:]))
