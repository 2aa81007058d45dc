"""A stop asked for by a signal: SIGTERM (or SIGHUP) or SIGINT sets a request that the training loop acts on at its next
iteration boundary (the ranks agree, save, and exit 128 + the signal). Until training begins there is nothing to
save, and a stop ends the process at once (``StopRequest.install``), even inside a call that waits for a rank that is
gone.

May import: the standard library and ``ftrain.errors``.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import typing

from ftrain.errors import Deliveries, raise_lost_stop, stop_code, stop_signals
from ftrain.terminal import leave_the_terminal


class StopRequest:
    """SIGTERM or SIGINT: stop at the next iteration boundary (the ranks agree, save, and exit 143 or 130, 128 + the
    signal, so that scripts and schedulers tell a stop from the end of training).

    Installed before anything slow starts, so an early signal is not lost. Repeated SIGTERMs are one request (a
    scheduler and torchrun may both forward it); a second SIGINT (Ctrl-C twice) stops at once, one delivered twice
    (``errors.Deliveries``: ``timeout -s INT``) does not.
    """

    def __init__(self) -> None:
        self.signal: int | None = None
        """The first stop signal this rank received."""
        self.deliveries = Deliveries()
        self._wakeup: tuple[int, int] | None = None
        """While starting: the pipe that Python's C-level signal handler writes each signal's number to."""

    @property
    def requested(self) -> bool:
        return self.signal is not None

    def install(self, at_start: typing.Callable[[int], None] = lambda signum: None) -> None:
        """Take SIGTERM and SIGINT over (``errors.stop_signals``: an ignored SIGINT stays so; one received before and
        lost on the way is raised first, ``errors.raise_lost_stop``), and until ``training()``, end this process at
        once on either, after ``at_start(signum)`` (its line): a Python handler runs only between the main thread's
        bytecodes, and a rendezvous or a collective that waits for a rank that is gone keeps it in C for its whole
        timeout (torchrun's SIGTERM went unanswered until its SIGKILL, 30 s later). A thread reads the numbers
        Python's own C-level handler writes to its wakeup pipe as the signal comes."""
        raise_lost_stop()
        for number in stop_signals():
            signal.signal(number, self._handle)
        read, write = os.pipe()
        os.set_blocking(write, False)
        signal.set_wakeup_fd(write, warn_on_full_buffer=False)
        self._wakeup = (read, write)
        threading.Thread(target=self._while_starting, args=(read, at_start), daemon=True, name="stop-at-start").start()

    def training(self) -> None:
        """Training begins: from here a stop waits for the iteration boundary, and saves."""
        if self._wakeup is not None:
            signal.set_wakeup_fd(-1)
            os.close(self._wakeup[1])  # the thread reads the end of the pipe and ends
            self._wakeup = None

    def exiting(self) -> None:
        """Saved, or nothing to save, and about to exit with the stop's code: once a rank has exited with it, torchrun
        SIGTERMs the others, and a SIGTERM while Python shuts down (its handlers gone) would kill a rank and read as
        a failure."""
        signal.signal(signal.SIGTERM, signal.SIG_IGN)

    def _while_starting(self, read: int, at_start: typing.Callable[[int], None]) -> None:
        with os.fdopen(read, "rb", buffering=0) as pipe:
            while number := pipe.read(1):
                if number[0] in stop_signals() and self._wakeup is not None:
                    at_start(number[0])
                    for stream in (sys.stdout, sys.stderr):
                        stream.flush()
                    os._exit(stop_code(number[0]))

    def _handle(self, signum: int, frame: object) -> None:
        if signum == signal.SIGHUP:  # a closed terminal: the ranks vote a SIGTERM, and print no more to it
            leave_the_terminal()
            signum = signal.SIGTERM
        if not self.deliveries.new(signum):
            return
        if self.requested and signum == signal.SIGINT:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            raise KeyboardInterrupt
        self.signal = self.signal or signum
