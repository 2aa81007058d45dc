"""The error file a failing worker leaves for torchrun and ``ftrain supervise``.

torchrun names one file per worker in ``TORCHELASTIC_ERROR_FILE`` and reads it, when the worker fails, in the JSON
of torch's ``@record`` machinery: ``{"message": {"message": ..., "extraInfo": {"py_callstack": ...,
"timestamp": ...}}}``. torchrun's failure report shows ``py_callstack``; the supervisor shows ``message``, one line.
A worker refusing its input says so in one line, once (rank 0 prints it; every rank records it); a worker that
crashes records its exception and keeps its traceback.

Torch-free: the CLI writes it in every worker, the supervisor reads what torchrun passes on.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

from ftrain.files import replace_text

ENV = "TORCHELASTIC_ERROR_FILE"
RECORDED_AT = "ftrain_recorded_at"
"""Our key in ``extraInfo``: when the error was recorded, to the microsecond (torch's ``timestamp`` has seconds)."""
REPORTED = "ftrain_reported"
"""Our key in ``extraInfo``: true where the worker explained the failure itself (``report``), in one line."""


def report(message: str) -> None:
    """A failure the worker explains itself (bad input, checkpoints that cannot be saved): ``ftrain: error:
    message`` on stderr, from rank 0 only under torchrun (every rank usually fails alike), and in the error file."""
    line = f"ftrain: error: {message}"
    if os.environ.get("RANK", "0") == "0":
        print(line, file=sys.stderr, flush=True)
    _write(message, line, reported=True)


def record_stop(message: str) -> None:
    """A stop that ends the worker before it trained: the line and its time go into the error file, so that of ranks
    ending alike the one stopped first is named (the others were stopped because it ended)."""
    _write(message, message)


def says_its_stop() -> bool:
    """Whether this worker prints the line of a stop that ends it before it trained: rank 0 alone (the others'
    stop is the same one, or torchrun's after one rank ended), and not when a worker of the same launcher has already
    explained its failure: torchrun stopped this one because that one ended, and that worker's line is the run's
    one line. torchrun gives each worker ``<log dir>/<run id>/attempt_<n>/<local rank>/error.json``; the file of a
    worker that explained its failure is there before torchrun, seeing it end, stops the others."""
    if os.environ.get("RANK", "0") != "0":
        return False
    mine = os.environ.get(ENV)
    if not mine:
        return True
    mine = Path(mine)
    return not any(reported(_read(other)) for other in mine.parent.parent.glob(f"*/{mine.name}") if other != mine)


def record_exception(error: BaseException) -> None:
    """An exception about to end the worker: its one-line summary and its traceback go into the error file."""
    _write(f"{type(error).__name__}: {error}", traceback.format_exc())


def message(data: object) -> str | None:
    """The one-line message in an error file's JSON (None if it holds none)."""
    text = data.get("message") if isinstance(data, dict) else None
    if isinstance(text, dict):
        text = text.get("message")
    if not isinstance(text, str):
        return None
    return " ".join(text.split()) or None


def reported(data: object) -> bool:
    """Whether an error file's JSON holds a failure the worker explained itself (``report``), not a crash."""
    return _extra_info(data).get(REPORTED) is True


def recorded_at(data: object) -> float:
    """When the worker recorded the error in an error file's JSON (epoch seconds; infinity if not known). A rank that
    fails because another one did (a broken connection, a peer gone from shared memory) records its error after the
    failure that caused it: the earliest record names the cause."""
    value = _extra_info(data).get(RECORDED_AT)
    return float(value) if isinstance(value, int | float) else math.inf


def _read(path: Path) -> object:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _extra_info(data: object) -> dict:
    info = data.get("message") if isinstance(data, dict) else None
    info = info.get("extraInfo") if isinstance(info, dict) else None
    return info if isinstance(info, dict) else {}


def _write(summary: str, callstack: str, reported: bool = False) -> None:
    path = os.environ.get(ENV)
    if not path:
        return
    now = time.time()
    info = {"py_callstack": callstack, "timestamp": str(int(now)), RECORDED_AT: now, REPORTED: reported}
    with contextlib.suppress(OSError):
        replace_text(path, json.dumps({"message": {"message": summary, "extraInfo": info}}))
