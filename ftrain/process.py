"""A cold start and a clean exit, cheaper: most of the CPU of a short ftrain process goes into importing torch and
MuJoCo and into tearing down what they made (docs/speed.md, "Start-up and exit", has the figures).

Owns ``imports()``, around the heavy imports: Python's cyclic collector off while they run, then what they made
frozen (``gc.freeze``), so later collections skip it and a fork of the warm pool does not copy its pages, and a
Ctrl-C or SIGTERM held until they are done; and ``exit_fast``, which ends a process as multiprocessing ends its
children, without the interpreter's teardown.
Promises: nothing that is trained depends on when the collector runs; an exit flushes what Python and C printed.
Imports the standard library and ``ftrain.errors``.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import gc
import os
import signal
import sys
import threading
from collections.abc import Iterator
from typing import NoReturn

from ftrain.errors import raise_stop


@contextlib.contextmanager
def imports() -> Iterator[None]:
    """Around the imports of the heavy libraries: without the cyclic garbage collector, then what they made frozen.
    A Ctrl-C, SIGTERM or SIGHUP meanwhile raises its exception once they are done (``errors.stop_signal``): raised
    inside a library's import, it may come out as that library's ImportError, or be swallowed by an ``except
    ImportError`` of an optional one. It is raised whatever the imports raised: the stop is why (pyGLFW reads each
    library's version in a child process, which a stop to the process group ends, and then fails its import)."""
    enabled, held = gc.isenabled(), []
    gc.disable()
    ours = (raise_stop, signal.default_int_handler)
    main = threading.current_thread() is threading.main_thread()
    stops = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    holding = {number: handler for number in stops if main and (handler := signal.getsignal(number)) in ours}
    for number in holding:
        signal.signal(number, lambda signum, frame: held.append(signum))
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()
        for number, handler in holding.items():
            signal.signal(number, handler)
        if held:  # also where an import failed meanwhile: a library's child, signalled with its group, ended with it
            holding[held[0]](held[0], None)


def exit_fast(code: int | None, died_of: int | None = None) -> NoReturn:
    """End this process after the threads that keep a process alive (``threading._shutdown``, as a normal exit does;
    it also stops idle thread pools), the exit functions (``atexit``: logging's flush, trackers, temporary
    directories) and a flush of Python's and C's standard streams, but without tearing the interpreter down.
    ``died_of``: end by that signal instead (as Python ends on a KeyboardInterrupt it did not handle: killed by
    SIGINT). Files still open unflushed would lose data here: ftrain closes what it writes."""
    threading._shutdown()
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    ctypes.CDLL(None).fflush(None)  # what C code (MuJoCo, gloo) printed through stdio
    if died_of is not None:
        signal.signal(died_of, signal.SIG_DFL)
        os.kill(os.getpid(), died_of)
    os._exit(code or 0)
