"""Local files written and deleted as ``storage.py`` needs them: complete whenever visible, and durable (fsync)."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import threading


def delete(path: str) -> None:
    """Delete a file, or a directory with everything below it."""
    if os.path.isdir(path) and not os.path.islink(path):
        shutil.rmtree(path)
    else:
        os.remove(path)


def delete_files(directory: str, paths: list[str]) -> bool:
    """Delete ``paths`` (those that exist) and then ``directory`` if that left it empty: whether it did."""
    for path in paths:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)
    try:
        os.rmdir(directory)
    except FileNotFoundError:
        pass
    except OSError as error:
        if error.errno not in (errno.ENOTEMPTY, errno.EEXIST):  # POSIX allows either for a non-empty directory
            raise
        return False
    return True


def write(path: str, data: bytes, exclusive: bool) -> None:
    """Write and fsync a local file (and its directory). ``exclusive``: the data goes to a temporary name in the same
    directory, which is then linked to ``path`` (FileExistsError if it exists), so the file is complete whenever it is
    visible and a failed create leaves nothing under ``path``."""
    directory = os.path.dirname(path)
    os.makedirs(directory, exist_ok=True)
    target = f"{path}.tmp-{os.getpid()}-{threading.get_ident()}" if exclusive else path
    fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        with os.fdopen(fd, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        if target != path:
            os.link(target, path)
    finally:
        if target != path:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(target)
    dir_fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)
