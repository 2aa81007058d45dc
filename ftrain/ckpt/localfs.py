"""Local files written and deleted as ``storage.py`` needs them: complete whenever visible, and durable (fsync)."""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
import threading

SHARED_FILE_SYSTEMS = frozenset(
    {"nfs", "nfs4", "cifs", "smb3", "smbfs", "9p", "afs", "lustre", "gpfs", "beegfs", "ceph", "glusterfs", "fuse"}
)
"""File system types whose listings may lack what another host wrote seconds ago (NFS caches lookups and
attributes), and FUSE, whatever serves it (s3fs, gcsfuse, sshfs...)."""


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


def shared(path: str) -> bool:
    """Whether ``path`` lies on a network or FUSE file system: the type of the deepest mount above it."""
    path, deepest, kind = os.path.realpath(path), "", ""
    with contextlib.suppress(OSError), open("/proc/self/mounts") as mounts:
        for line in mounts:
            fields = line.split()
            point = fields[1].replace("\\040", " ") if len(fields) > 2 else ""
            if point and (path == point or path.startswith(point.rstrip("/") + "/")) and len(point) >= len(deepest):
                deepest, kind = point, fields[2]
    return kind.partition(".")[0] in SHARED_FILE_SYSTEMS


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
