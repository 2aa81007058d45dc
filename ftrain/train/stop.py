"""A stop asked for by a signal: SIGTERM or SIGINT sets a request that the training loop acts on at its next
iteration boundary (the ranks agree, save, and exit 128 + the signal).

May import: the standard library and ``ftrain.errors``.
"""

from __future__ import annotations

import signal

from ftrain.errors import Deliveries


class StoppedAtStart(Exception):
    """A stop request came while the run was starting, before it trained anything: nothing to save, every rank exits
    with the stop's code at once."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


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

    @property
    def requested(self) -> bool:
        return self.signal is not None

    def install(self) -> None:
        signal.signal(signal.SIGTERM, self._handle)
        signal.signal(signal.SIGINT, self._handle)

    def exiting(self) -> None:
        """Saved, or nothing to save, and about to exit with the stop's code: once a rank has exited with it, torchrun
        SIGTERMs the others, and a SIGTERM while Python shuts down (its handlers gone) would kill a rank and read as
        a failure."""
        signal.signal(signal.SIGTERM, signal.SIG_IGN)

    def _handle(self, signum: int, frame: object) -> None:
        if not self.deliveries.new(signum):
            return
        if self.requested and signum == signal.SIGINT:
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            raise KeyboardInterrupt
        self.signal = self.signal or signum
