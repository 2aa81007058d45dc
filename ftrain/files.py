"""Files written whole or not at all.

A reader of a small state file (torchrun's agent reading a worker's error file, the supervisor a heartbeat or
torchrun's failures) sees the old content or the new, never part of it, whenever the writer is killed: the text goes
to a temporary file beside the target, named after the writing process and thread, and ``os.replace`` puts it in
place. A writer killed mid-write leaves at most that temporary file, which no reader looks at (its name starts with a
dot). Standard library only: the CLI, the workers and the supervisor all import it.
"""

from __future__ import annotations

import contextlib
import os
import threading
from pathlib import Path


def replace_text(path: str | os.PathLike, text: str) -> None:
    """Make ``path`` hold ``text``, atomically (see the module)."""
    replace_file(path, text.encode())


def replace_file(path: str | os.PathLike, data: bytes, durable: bool = False) -> None:
    """Make ``path`` hold ``data``, atomically (see the module); ``durable``: on disk before this returns, the rename
    too (a record that a power cut must not take back: the storage's lease). Raises OSError as writing does, and then
    leaves no temporary file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}-{threading.get_native_id()}.tmp")
    try:
        with open(tmp, "wb") as file:
            file.write(data)
            if durable:
                file.flush()
                os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    if durable:
        directory = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)
