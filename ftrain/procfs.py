"""What Linux's ``/proc`` says about a process: the supervisor, its workers, the benchmarks and the tests read it the
same way."""

from __future__ import annotations

import functools
import os
import socket
from dataclasses import dataclass
from pathlib import Path


def stat_fields(pid: int) -> list[str]:
    """The fields of ``/proc/<pid>/stat`` after the command name, state first (``[0]``), parent pid ``[1]``, user
    and system CPU ticks ``[11]``, ``[12]``, start time ``[19]``; empty once the process is gone. The command name,
    in parentheses, may itself hold spaces and parentheses: the fields start after the last ``)``."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return []


def state(pid: int) -> str:
    """The kernel's state letter for ``pid`` (R running, S sleeping, D in the kernel, T stopped, Z a zombie), or
    ``gone``."""
    fields = stat_fields(pid)
    return fields[0] if fields else "gone"


def start_time(pid: int) -> str | None:
    """When process ``pid`` started (clock ticks after boot), None once it has ended (gone, or a zombie its parent, or
    an init that reaps late, has not collected yet): with the pid, it names one process for good (a pid the kernel
    hands out again has another start time)."""
    fields = stat_fields(pid)
    return fields[19] if fields and fields[0] not in ("Z", "X") else None


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time of process ``pid`` so far."""
    fields = stat_fields(pid)
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def resident_bytes() -> int:
    """This process's resident memory now (``/proc/self/statm``)."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def available_memory() -> int | None:
    """The bytes of memory this process can still take: the machine's ``MemAvailable``, or less where a cgroup (v2) of
    this process, a container's or a job's, has its limit nearer; None where ``/proc/meminfo`` does not say."""
    try:
        meminfo = Path("/proc/meminfo").read_text()
    except OSError:
        return None
    found = [int(line.split()[1]) * 1024 for line in meminfo.splitlines() if line.startswith("MemAvailable:")]
    if not found:
        return None
    room = [found[0]]
    try:
        group = Path("/proc/self/cgroup").read_text().partition("0::")[2].split("\n")[0]
    except OSError:
        group = ""
    cgroup = Path("/sys/fs/cgroup") / group.strip("/")
    for directory in (cgroup, *cgroup.parents) if group else ():
        try:
            limit, used = (directory / "memory.max").read_text().strip(), (directory / "memory.current").read_text()
        except OSError:
            continue
        if limit != "max":
            room.append(int(limit) - int(used))
        if directory == Path("/sys/fs/cgroup"):
            break
    return max(0, min(room))


def read(pid: int, name: str) -> bytes:
    """``/proc/<pid>/<name>`` (``cmdline``, ``environ``, ...); empty once the process is gone or if it is not ours."""
    try:
        return Path(f"/proc/{pid}/{name}").read_bytes()
    except OSError:
        return b""


def pids() -> list[int]:
    """Every process's pid, as /proc lists them now."""
    return [int(entry.name) for entry in Path("/proc").iterdir() if entry.name.isdigit()]


def with_environment(name: str, value: str) -> list[int]:
    """Live processes whose environment holds ``name=value`` (a zombie's environment is unreadable)."""
    needle = f"{name}={value}".encode()
    return [pid for pid in pids() if needle in read(pid, "environ").split(b"\0")]


def descendants(pid: int) -> list[int]:
    """Every live process below ``pid`` (torchrun starts each worker in a session of its own, so a process group
    kill does not reach them): what the tests and benchmarks kill to lose a whole node at once."""
    children: dict[int, list[int]] = {}
    for child in pids():
        if fields := stat_fields(child):
            children.setdefault(int(fields[1]), []).append(child)
    found, todo = [], [pid]
    while todo:
        for child in children.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def lock_holders(fd: int) -> list[int]:
    """The processes of this pid namespace holding a lock (``flock`` or POSIX) of the file open as ``fd``, by
    ``/proc/locks``, which names the file by device and inode (a waiter's line, marked ``->``, holds nothing; another
    namespace's holder shows pid 0). Where no line has the device (btrfs and overlayfs list another one than ``stat``
    gives), the inode alone."""
    stat = os.fstat(fd)
    device = f"{os.major(stat.st_dev):02x}:{os.minor(stat.st_dev):02x}"
    try:
        lines = Path("/proc/locks").read_text().splitlines()
    except OSError:
        return []
    held = [fields for fields in map(str.split, lines) if len(fields) > 5 and fields[1] != "->"]
    files = [(int(fields[4]), fields[5].rpartition(":")) for fields in held]
    mine = [(pid, dev) for pid, (dev, _, inode) in files if inode == str(stat.st_ino)]
    exact = [pid for pid, dev in mine if dev == device]
    return [pid for pid in (exact or [pid for pid, _ in mine]) if pid > 0]


def describe(pid: int) -> str:
    """``pid`` as a person finds it in ``ps``: its command line (an ftrain process's names its role) and, if it is
    stopped, that it is."""
    command = " ".join(read(pid, "cmdline").decode(errors="replace").replace("\0", " ").split())[:120] or "gone"
    return f"process {pid} ({command}{', stopped' if state(pid) in ('T', 't') else ''})"


@dataclass(frozen=True)
class Process:
    """A process, as precisely as its host lets another process recognise it."""

    host: str
    pid: int
    start: int
    """Its start time in clock ticks after boot (``/proc/<pid>/stat``): a reused pid has another."""
    boot: str
    """The host's boot id: a reboot changes it."""
    pidns: str
    """Its pid namespace: pids of another namespace (another container) cannot be looked up here."""

    @classmethod
    def current(cls) -> Process:
        host, boot, pidns = _here()
        pid = os.getpid()
        return cls(host, pid, int(start_time(pid) or 0), boot, pidns)

    def running(self) -> bool | None:
        """Seen from here: whether it still runs; None if this host cannot tell (another host, another namespace)."""
        host, boot, pidns = _here()
        if self.host != host or self.boot != boot or not boot or self.pidns != pidns:
            return None  # another host (a host name says too little: cloned machines share one), or a reboot since
        fields = stat_fields(self.pid)
        return bool(fields) and fields[0] != "Z" and int(fields[19]) == self.start  # a zombie has ended

    def describe(self) -> str:
        return f"pid {self.pid} on host {self.host}"


@functools.cache
def _here() -> tuple[str, str, str]:
    """This host's name and boot id, and this process's pid namespace (boot id and namespace "" where /proc does not
    tell: then no process is ever seen gone, leases only expire)."""
    try:
        boot, pidns = Path("/proc/sys/kernel/random/boot_id").read_text().strip(), os.readlink("/proc/self/ns/pid")
    except OSError:
        boot = pidns = ""
    return socket.gethostname(), boot, pidns
