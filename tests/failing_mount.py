"""A file system of the tests' own that fails on demand, as a hung NFS or a FUSE mount whose server went away does:
a passthrough of a backing directory, mounted with FUSE (mfusepy on libfuse) by a child process, that answers every
operation with EIO while its switch file (outside the mount) exists. ``failing_mount(directory)`` mounts it, skips
the test where FUSE cannot be used, and unmounts it at the end, whatever happened.

Run as a script, this is the child: ``python failing_mount.py BACKING MOUNTPOINT SWITCH`` serves until unmounted.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import errno
import functools
import importlib.util
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

MOUNT_TIMEOUT = 30.0
"""Seconds the child gets to mount (it imports mfusepy and libfuse first)."""
STAT_FIELDS = ("st_mode", "st_ino", "st_nlink", "st_uid", "st_gid", "st_size", "st_blocks")


@dataclass(frozen=True)
class FailingMount:
    """A mounted failing file system: ``path`` is the mount point; ``fail`` and ``recover`` switch its errors."""

    path: Path
    switch: Path

    def fail(self) -> None:
        self.switch.touch()

    def recover(self) -> None:
        self.switch.unlink(missing_ok=True)


@contextlib.contextmanager
def failing_mount(directory: Path) -> Iterator[FailingMount]:
    """A failing file system mounted at ``directory/mnt`` (its files in ``directory/backing``, the child's output in
    ``directory/fuse.log``), working until ``fail``; unmounted at the end. Skips where FUSE cannot be used."""
    why = unusable()
    if why is not None:
        pytest.skip(f"FUSE cannot be used here: {why}")
    directory = directory.resolve()  # as the mount table names it
    backing, mountpoint, switch, log = (directory / name for name in ("backing", "mnt", "failing", "fuse.log"))
    backing.mkdir(parents=True)
    mountpoint.mkdir()
    command = [sys.executable, __file__, str(backing), str(mountpoint), str(switch)]
    with log.open("wb") as output:
        proc = subprocess.Popen(command, stdout=output, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + MOUNT_TIMEOUT
        while not mounted(mountpoint) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        if not mounted(mountpoint):
            lines = log.read_text(errors="replace").strip().splitlines() or ["no output"]
            pytest.skip(f"FUSE cannot be used here: mounting {mountpoint} failed ({lines[-1]})")
        yield FailingMount(mountpoint, switch)
    finally:
        switch.unlink(missing_ok=True)
        unmount(mountpoint)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def unusable() -> str | None:
    """Why this machine cannot mount the failing file system, None if it can."""
    if not os.path.exists("/dev/fuse"):
        return "no /dev/fuse (a container needs --device /dev/fuse)"
    if os.geteuid() != 0:
        return "the tests mount it as root, and this is not root"
    if importlib.util.find_spec("mfusepy") is None:
        return "mfusepy is not installed (pip install -e '.[test]')"
    if not (ctypes.util.find_library("fuse3") or ctypes.util.find_library("fuse")):
        return "libfuse is not installed (apt-get install fuse3: launch/setup.sh does with FTRAIN_TEST_DEPS=1)"
    return None


def mounted(mountpoint: Path) -> bool:
    """Whether something is mounted at ``mountpoint``, from the mount table: a mount whose server died still is, and
    a stat of it fails."""
    with open("/proc/self/mounts") as mounts:
        return any(line.split()[1] == str(mountpoint) for line in mounts)


def unmount(mountpoint: Path) -> None:
    """Unmount, lazily where a process still uses the mount (a test that failed may leave one)."""
    for command in (["fusermount3", "-u"], ["fusermount", "-u"], ["umount"], ["umount", "-l"]):
        if not mounted(mountpoint):
            return
        if shutil.which(command[0]):
            subprocess.run([*command, str(mountpoint)], capture_output=True)


def failable(operation: Callable[..., Any]) -> Callable[..., Any]:
    """The operation, answering EIO while the switch file exists."""

    @functools.wraps(operation)
    def wrapper(self: Passthrough, *args: Any) -> Any:
        if os.path.exists(self.switch):
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        return operation(self, *args)

    return wrapper


class Passthrough:
    """The operations of the file system, as mfusepy calls them (a class of its own, not a subclass of mfusepy's
    ``Operations``: the tests import this module where mfusepy may be missing, to skip). Each acts on the same path
    below ``backing``, file handles being the backing files' descriptors. Only ``release`` never fails: the kernel
    ignores its answer, and the descriptor would leak."""

    use_ns = True
    """Times in nanoseconds (mfusepy's float seconds are deprecated)."""

    def __init__(self, backing: str, switch: str) -> None:
        self.backing = backing
        self.switch = switch

    def _real(self, path: str) -> str:
        return os.path.join(self.backing, path.lstrip("/"))

    @failable
    def getattr(self, path: str, fh: int | None = None) -> dict[str, int]:
        st = os.lstat(self._real(path)) if fh is None else os.fstat(fh)
        times = {f"st_{name}": getattr(st, f"st_{name}_ns") for name in ("atime", "mtime", "ctime")}
        return {**{field: getattr(st, field) for field in STAT_FIELDS}, **times}

    @failable
    def readdir(self, path: str, fh: int) -> list[str]:
        return [".", "..", *os.listdir(self._real(path))]

    @failable
    def mkdir(self, path: str, mode: int) -> None:
        os.mkdir(self._real(path), mode)

    @failable
    def rmdir(self, path: str) -> None:
        os.rmdir(self._real(path))

    @failable
    def create(self, path: str, mode: int, flags: int) -> int:
        return os.open(self._real(path), flags | os.O_CREAT, mode)

    @failable
    def open(self, path: str, flags: int) -> int:
        return os.open(self._real(path), flags)

    @failable
    def read(self, path: str, size: int, offset: int, fh: int) -> bytes:
        return os.pread(fh, size, offset)

    @failable
    def write(self, path: str, data: bytes, offset: int, fh: int) -> int:
        return os.pwrite(fh, data, offset)

    @failable
    def flush(self, path: str, fh: int) -> None:
        """Each ``close`` of a descriptor: nothing to do, as writes went straight to the backing file."""

    def release(self, path: str, fh: int) -> None:
        os.close(fh)

    @failable
    def fsync(self, path: str, datasync: int, fh: int) -> None:
        (os.fdatasync if datasync else os.fsync)(fh)

    @failable
    def fsyncdir(self, path: str, datasync: int, fh: int) -> None:
        fd = os.open(self._real(path), os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)

    @failable
    def unlink(self, path: str) -> None:
        os.unlink(self._real(path))

    @failable
    def rename(self, old: str, new: str) -> None:
        os.rename(self._real(old), self._real(new))

    @failable
    def link(self, target: str, source: str) -> None:
        """``target``: the new name of the file ``source`` (mfusepy's order)."""
        os.link(self._real(source), self._real(target))

    @failable
    def truncate(self, path: str, length: int, fh: int | None = None) -> None:
        if fh is None:
            os.truncate(self._real(path), length)
        else:
            os.ftruncate(fh, length)

    @failable
    def utimens(self, path: str, times: tuple[int, int] | None = None) -> None:
        os.utime(self._real(path), ns=times)

    @failable
    def chmod(self, path: str, mode: int) -> None:
        os.chmod(self._real(path), mode)

    @failable
    def chown(self, path: str, uid: int, gid: int) -> None:
        os.chown(self._real(path), uid, gid)

    @failable
    def statfs(self, path: str) -> dict[str, int]:
        st = os.statvfs(self._real(path))
        names = ("bsize", "frsize", "blocks", "bfree", "bavail", "files", "ffree", "favail", "flag", "namemax")
        return {f"f_{name}": getattr(st, f"f_{name}") for name in names}


def serve(backing: str, mountpoint: str, switch: str) -> None:
    """Mount and serve until unmounted. The kernel caches no names nor attributes (each look reaches the switch), and
    without ``kernel_cache`` each open drops the file's cached pages: every read after an open is asked too."""
    import mfusepy

    timeouts = {"entry_timeout": 0, "attr_timeout": 0, "negative_timeout": 0}
    mfusepy.FUSE(Passthrough(backing, switch), mountpoint, foreground=True, fsname="failing_mount", **timeouts)


if __name__ == "__main__":
    serve(*sys.argv[1:4])
