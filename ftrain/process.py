"""A cold start and a clean exit, cheaper: most of the CPU a short ftrain process spends goes into importing torch and
into tearing down what it imported.

Measured on the 2-core machine (a cold ``python -m ftrain train`` of the smoke config, 2 iterations: about 8 CPU-s):

- Python's cyclic garbage collector runs dozens of times while torch, tensordict (and through it ``torch._dynamo``)
  and MuJoCo import, and each full pass walks every object imported so far: about 1.2 of the 5 CPU-s that importing
  ``ftrain.train.trainer`` takes. ``imports()`` keeps the collector off while they import, then freezes what they
  made (``gc.freeze``): later collections, those of the training loop included, skip those objects, and a process
  forked from the warm pool does not copy the pages that a collection would have written to (the recipe of the
  ``gc.freeze`` documentation). Nothing that is trained depends on when the collector runs.
- Interpreter teardown frees those objects one by one: about 1.2 CPU-s more, and in a fork of the warm pool it also
  copies all of its memory. ``exit_fast`` ends a process as multiprocessing ends its children instead.
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


@contextlib.contextmanager
def imports() -> Iterator[None]:
    """Around the imports of the heavy libraries: without the cyclic garbage collector, then what they made frozen."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


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
