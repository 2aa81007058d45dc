"""A live progress line for people waiting at a terminal; silent when output goes to a file or a pipe."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import TextIO

REDRAW_S = 0.25
"""Seconds between two redraws of a count: often enough to look alive, rarely enough to cost nothing."""


class Progress:
    """``show`` rewrites one line in place (carriage return); ``count`` shows how far a piece of work is, with an
    ETA; ``clear`` removes the line before normal output."""

    def __init__(self, stream: TextIO | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.stream = stream or sys.stdout
        self.live = self.stream.isatty()
        self.clock = clock
        self._width = 0
        self._started: tuple[str, float] | None = None
        """The work being counted (its label) and when its count began."""
        self._drawn = 0.0

    def show(self, text: str) -> None:
        if self.live:
            self.stream.write("\r" + text.ljust(self._width))
            self.stream.flush()
            self._width = len(text)

    def count(self, label: str, done: int, total: int, unit: str, note: str = "") -> None:
        """``label: done/total unit (percent), ETA`` (``note`` after it), the ETA from the pace since the count of
        ``label`` began; ``total`` is an upper bound where the work may end early (e.g. an episode's step limit)."""
        now = self.clock()
        if self._started is None or self._started[0] != label:
            self._started = (label, now)
        if not self.live or (self._width and now - self._drawn < REDRAW_S and done < total):
            return  # drawn at once where no line shows, then every REDRAW_S, and at the end
        self._drawn = now
        elapsed = now - self._started[1]
        eta = f", ETA {duration(elapsed / done * (total - done))}" if done and elapsed > 0 else ""
        self.show(f"{label}: {done:,}/{total:,} {unit} ({100 * done / max(total, 1):.0f}%){eta}{note}")

    def clear(self) -> None:
        if self.live and self._width:
            self.stream.write("\r" + " " * self._width + "\r")
            self.stream.flush()
            self._width = 0


def duration(seconds: float) -> str:
    """``42s``, ``3m05s``, ``1h02m``."""
    seconds = int(seconds)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m" if hours else f"{minutes}m{secs:02d}s" if minutes else f"{secs}s"
