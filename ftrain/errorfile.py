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
import os
import sys
import time
import traceback
from pathlib import Path

ENV = "TORCHELASTIC_ERROR_FILE"


def report(message: str) -> None:
    """A failure the worker explains itself (bad input, checkpoints that cannot be saved): ``ftrain: error:
    message`` on stderr, from rank 0 only under torchrun (every rank usually fails alike), and in the error file."""
    line = f"ftrain: error: {message}"
    if os.environ.get("RANK", "0") == "0":
        print(line, file=sys.stderr, flush=True)
    _write(message, line)


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


def _write(summary: str, callstack: str) -> None:
    path = os.environ.get(ENV)
    if not path:
        return
    info = {"py_callstack": callstack, "timestamp": str(int(time.time()))}
    with contextlib.suppress(OSError):
        Path(path).write_text(json.dumps({"message": {"message": summary, "extraInfo": info}}))
