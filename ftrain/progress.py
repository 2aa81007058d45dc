"""A live progress line for people waiting at a terminal; silent when output goes to a file or a pipe."""

from __future__ import annotations

import sys
from typing import TextIO


class Progress:
    """``show`` rewrites one line in place (carriage return); ``clear`` removes it before normal output."""

    def __init__(self, stream: TextIO | None = None) -> None:
        self.stream = stream or sys.stdout
        self.live = self.stream.isatty()
        self._width = 0

    def show(self, text: str) -> None:
        if self.live:
            self.stream.write("\r" + text.ljust(self._width))
            self.stream.flush()
            self._width = len(text)

    def clear(self) -> None:
        if self.live and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0
