"""The progress line: live on a terminal, silent into a file or a pipe."""

from __future__ import annotations

import io
import os
import pty

from ftrain.progress import Progress


def test_a_terminal_sees_the_line_rewritten_and_cleared() -> None:
    ours, theirs = pty.openpty()
    with os.fdopen(theirs, "w") as terminal:
        progress = Progress(terminal)
        progress.show("rendering: 25 frames")
        progress.show("rendering: 50 frames")
        progress.clear()
        terminal.flush()
        written = os.read(ours, 1000).decode()
    os.close(ours)
    assert written == "\rrendering: 25 frames\rrendering: 50 frames\r                    \r"


def test_a_file_or_pipe_sees_nothing() -> None:
    stream = io.StringIO()
    progress = Progress(stream)
    progress.show("rendering: 25 frames")
    progress.clear()
    assert stream.getvalue() == ""
