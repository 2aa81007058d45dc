"""One tracker's background thread: rows go through a bounded queue, so a slow or unreachable tracker never holds up
training, and each row is sent once, past the last step the tracker holds. A resumed run redoes the iterations past
its checkpoint, which a tracker may hold already (being bit for bit, with the values it holds): they are skipped. A
tracker may also have lost rows up to the checkpoint (a killed process had not sent or flushed them): they are sent
again from the run's own record of them first. A failure is one warning line, after which the tracker is left alone:
nothing a tracker does reaches the training loop."""

from __future__ import annotations

import atexit
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol

QUEUE_ROWS = 1000
"""Rows waiting for a tracker before new ones are dropped (with one warning)."""
CLOSE_SECONDS = 10.0
"""How long the end of a run waits for a tracker that takes nothing of what is queued: one that still takes rows (a
slow one, resending a run's rows on a busy machine) is waited for, up to ``CLOSE_AT_MOST``."""
CLOSE_AT_MOST = 60.0
GOES_ON = "training goes on without it"


@dataclass(frozen=True)
class RunInfo:
    """What a tracker is told about a training run, as plain data (no trainer)."""

    run_id: str
    """ftrain's id of the tracker run: W&B's run id, an MLflow tag (MLflow makes its own ids)."""
    name: str
    config: dict
    """The resolved config, credentials redacted (``Config.public_dict``)."""
    identity: dict[str, str | int]
    """Config hash, storage URL (redacted), world size of this start."""
    log_dir: str


class Tracker(Protocol):
    """What a tracker module implements (``ftrain.track.wandb_run``, ``ftrain.track.mlflow_run``)."""

    name: str

    def open(self) -> int:
        """Start or continue the run; the last step it holds (-1: none)."""

    def log(self, step: int, values: dict[str, float]) -> None: ...

    def close(self, finished: bool) -> None:
        """``finished``: the training run is complete (else stopped, to be continued)."""


class Sender:
    def __init__(
        self,
        tracker: Tracker,
        earlier: Callable[[int], Iterable[tuple[int, dict[str, float]]]],
        extra: Callable[[], dict[str, float]],
        warn: Callable[[str], None],
    ) -> None:
        """``earlier(step)``: the rows of the iterations past ``step`` that this process will not redo; ``extra``:
        values added to every row as it is sent (the supervisor's totals so far)."""
        self.tracker = tracker
        self.earlier = earlier
        self.extra = extra
        self._warn = warn
        self._warned = False
        self._rows: queue.Queue[tuple[int, dict[str, float]]] = queue.Queue(QUEUE_ROWS)
        self._closing = threading.Event()
        self._finished = False
        self._sent = 0
        """Rows the tracker has taken: a close waits while it grows."""
        self._thread = threading.Thread(target=self._run, name=f"ftrain-{tracker.name}", daemon=True)
        self._thread.start()
        atexit.register(self.close, False)  # a worker ending on an error still hands over what is queued

    def send(self, step: int, values: dict[str, float]) -> None:
        """Never blocks: a full queue drops the row."""
        try:
            self._rows.put_nowait((step, values))
        except queue.Full:
            self.warn(f"it is {QUEUE_ROWS} iterations behind: dropping iterations from {step} on; {GOES_ON}")

    def close(self, finished: bool) -> None:
        """Let the thread send what is queued and end the tracker's run, while it takes rows (``CLOSE_SECONDS``)."""
        atexit.unregister(self.close)
        self._finished = finished
        self._closing.set()
        end, answering = time.monotonic() + CLOSE_AT_MOST, True
        while self._thread.is_alive() and answering and time.monotonic() < end:
            sent = self._sent
            self._thread.join(min(CLOSE_SECONDS, end - time.monotonic()))
            answering = self._sent != sent
        if self._thread.is_alive():
            late = (
                f"still sending {CLOSE_AT_MOST:g} s after"
                if answering
                else f"did not answer within {CLOSE_SECONDS:g} s of"
            )
            self.warn(f"{late} the end: {self._rows.qsize()} iterations not sent")

    def warn(self, problem: str) -> None:
        """One line per tracker and process, the first problem: the rest would only repeat it."""
        if not self._warned:
            self._warned = True
            self._warn(f"{self.tracker.name}: {problem}")

    def _run(self) -> None:
        try:
            last = self.tracker.open()
            for step, values in self.earlier(last):
                self._log(step, values)
            while not (self._closing.is_set() and self._rows.empty()):
                try:
                    step, values = self._rows.get(timeout=0.1)
                except queue.Empty:
                    continue
                if step > last:
                    self._log(step, values)
            self.tracker.close(self._finished)
        except Exception as error:  # any failure of the tracker: training does not depend on it
            self.warn(f"failed ({type(error).__name__}: {_first_line(error)}); {GOES_ON}")

    def _log(self, step: int, values: dict[str, float]) -> None:
        self.tracker.log(step, {**values, **self.extra()})
        self._sent += 1


def _first_line(error: Exception, limit: int = 600) -> str:
    """The error's first line; past ``limit`` characters, its start and its end (where a library puts its fix, as
    MLflow's "set MLFLOW_ALLOW_FILE_STORE=true") around an elision."""
    text = str(error).strip().splitlines()
    line = text[0] if text else ""
    return line if len(line) <= limit else f"{line[: limit // 2 - 3]} ... {line[-(limit // 2 - 2) :]}"
