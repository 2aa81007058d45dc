"""Standard output and error where they are a terminal, and what happens to them when it hangs up.

A terminal or SSH session that closes fails every later write to it (EIO). A run that prints its progress there must
not die of that before its save: not a lone ``ftrain train``, not a worker of ``ftrain supervise`` that prints in the
moment between the hang-up and the supervisor's SIGHUP, not a run whose SIGHUP never comes (``disown``, SIGHUP
ignored). ``outlive_a_hangup`` (at the start of each command) makes Python's writes to a terminal that hung up go to
/dev/null instead; ``leave_the_terminal`` (on SIGHUP) does the same at once, for what C code writes too. Output to a
file or a pipe is never touched. Imports nothing of ftrain.
"""

from __future__ import annotations

import contextlib
import errno
import io
import os
import sys

_terminal_fds: set[int] = set()
"""Standard output and error where they were a terminal at the command's start (once it hangs up, ``isatty`` fails)."""


def leave_the_terminal() -> None:
    """What is still written to the terminal goes to /dev/null from now on."""
    null = os.open(os.devnull, os.O_WRONLY)
    for fd in _terminal_fds:
        os.dup2(null, fd)
    os.close(null)


class _LeavesAHungUpTerminal(io.FileIO):
    """A terminal's file whose first write that fails with EIO (the terminal hung up) leaves the terminal and is
    written to /dev/null."""

    def write(self, data: bytes) -> int:
        try:
            return super().write(data)
        except OSError as error:
            if error.errno != errno.EIO:
                raise
            leave_the_terminal()
            return super().write(data)


def outlive_a_hangup() -> None:
    """Note which of standard output and error are a terminal now (a warm pool's fork got its streams after it imported
    ftrain), and give ``sys.stdout`` and ``sys.stderr`` on a terminal a file that leaves it once it hangs up."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        with contextlib.suppress(AttributeError, OSError, ValueError):  # not a file (a test's capture), or closed
            if not isinstance(stream, io.TextIOWrapper) or not os.isatty(fd := stream.fileno()):
                continue
            _terminal_fds.add(fd)
            if isinstance(getattr(stream.buffer, "raw", None), _LeavesAHungUpTerminal):
                continue
            stream.flush()
            raw = _LeavesAHungUpTerminal(fd, "w", closefd=False)
            setattr(
                sys,
                name,
                io.TextIOWrapper(
                    io.BufferedWriter(raw),
                    encoding=stream.encoding,
                    errors=stream.errors,
                    line_buffering=stream.line_buffering,
                    write_through=stream.write_through,
                ),
            )
