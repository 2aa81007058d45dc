"""The progress line: live on a terminal, silent into a file or a pipe."""

from __future__ import annotations

import io
import os
import pty
import select
import time

from ftrain.progress import Progress

WRITTEN = "\rrendering: 25 frames\rrendering: 50 frames\r                    \r"


def read_terminal(fd: int, size: int, timeout: float = 30.0) -> str:
    """What the terminal ``fd`` shows, read until ``size`` characters came or ``timeout`` passed: one ``os.read``
    returns what has arrived so far, which under load is part of it."""
    seen, deadline = b"", time.monotonic() + timeout
    while len(seen) < size and (left := deadline - time.monotonic()) > 0:
        if select.select([fd], [], [], left)[0]:
            seen += os.read(fd, size - len(seen))
    return seen.decode()


def test_a_terminal_sees_the_line_rewritten_and_cleared() -> None:
    ours, theirs = pty.openpty()
    with os.fdopen(theirs, "w") as terminal:
        progress = Progress(terminal)
        progress.show("rendering: 25 frames")
        progress.show("rendering: 50 frames")
        progress.clear()
        terminal.flush()
        written = read_terminal(ours, len(WRITTEN))
    os.close(ours)
    assert written == WRITTEN


def test_a_file_or_pipe_sees_nothing() -> None:
    stream = io.StringIO()
    progress = Progress(stream)
    progress.show("rendering: 25 frames")
    progress.clear()
    assert stream.getvalue() == ""


def test_a_count_shows_an_eta_from_its_pace_redrawn_at_most_every_quarter_second() -> None:
    times = iter([0.0, 0.1, 1.0, 1.1])
    ours, theirs = pty.openpty()
    with os.fdopen(theirs, "w") as terminal:
        progress = Progress(terminal, clock=lambda: next(times))
        for done in (0, 1, 2, 4):  # 1 comes 0.1 s after 0: not drawn
            progress.count("verifying", done, 4, "steps")
        progress.clear()
        terminal.flush()
        lines = ["verifying: 0/4 steps (0%)", "verifying: 2/4 steps (50%), ETA 1s"]
        lines.append("verifying: 4/4 steps (100%), ETA 0s")  # the end is drawn, however soon
        expected = "".join(f"\r{line}" for line in lines) + "\r" + " " * len(lines[-1]) + "\r"
        written = read_terminal(ours, len(expected))
    os.close(ours)
    assert written == expected
