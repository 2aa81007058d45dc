"""The warm pool (``ftrain/warm``) on its own: a real pool process, tied to this test process as to a supervisor,
and real stand-ins that hand their command over to it. Supervised runs use it by default: every test of
``ftrain supervise`` with the real trainer goes through it, and ``test_chaos.py`` compares them with cold runs."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from ftrain import lifeline, procfs
from ftrain.warm import address

from helpers import REPO, child_env, launch, wait_for

NOBODY = 65534
STAND_IN = "import sys; from ftrain.warm import handover; code = handover({entry!r}, {argv!r}); sys.exit(code)"
"""A stand-in: exit status None (0) when no pool took its command (it would then run it cold)."""
COLD = 0
STRANGER = """
import json, socket, struct, sys
connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
connection.connect("\\0ftrain-warm-" + sys.argv[1].replace(":", "-"))
request = {"entry": "train", "argv": ["train"], "sys_argv": ["ftrain"], "env": {}, "cwd": "/", "umask": 18}
data = json.dumps(request).encode()
try:
    socket.send_fds(connection, [struct.pack("!I", len(data))], [0, 1, 2])
    connection.sendall(data)
    answer = connection.recv(100)
except (BrokenPipeError, ConnectionResetError):  # closed before the request was all sent
    answer = b""
print("forked" if answer else "refused")
"""
"""The pool's protocol spoken by hand, by the system's Python (another user may not read this repo's environment)."""
SYSTEM_PYTHON = shutil.which("python3", path="/usr/bin:/bin")


@pytest.fixture
def pool():
    """A warm pool whose supervisor is this test process."""
    supervisor = lifeline.supervisor_env()
    proc = launch([sys.executable, "-u", "-m", "ftrain.warm", "serve"], cwd=REPO, env=child_env(supervisor))
    name = address(supervisor[lifeline.SUPERVISOR_ENV]).replace("\0", "@")  # how the kernel lists abstract names
    wait_for(lambda: name in Path("/proc/net/unix").read_text(), "the pool's socket", timeout=60)
    yield proc
    proc.kill()
    proc.wait()


def stand_in(entry: str, argv: list[str], **popen: object) -> subprocess.Popen:
    code = STAND_IN.format(entry=entry, argv=argv)
    env = child_env({**lifeline.supervisor_env(), "FTRAIN_TEST_MARK": "from-the-stand-in"})
    return subprocess.Popen([sys.executable, "-c", code], cwd=popen.pop("cwd", REPO), env=env, **popen)


def test_the_pool_runs_the_command_with_the_stand_ins_streams_directory_environment_and_exit_code(pool, tmp_path):
    """``ftrain --version`` exits 0 by SystemExit after printing to the stand-in's stdout; a usage error exits 2 with
    argparse's line on the stand-in's stderr."""
    version = stand_in("train", ["--version"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path)
    out, err = version.communicate(timeout=120)
    assert version.returncode == 0 and out.decode().startswith("ftrain "), (out, err)

    wrong = stand_in("train", ["train"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = wrong.communicate(timeout=60)
    assert wrong.returncode == 2 and b"ftrain train: error: the following arguments are required: config" in err, (
        out,
        err,
    )


def test_the_fork_lives_in_the_stand_ins_directory_and_environment_and_dies_with_it(pool, tmp_path):
    """A fork that runs (here torchrun's stand-in for a worker that sleeps) sees the stand-in's working directory
    and environment; SIGSTOPped and then left by its SIGKILLed stand-in, the pool SIGKILLs it; SIGKILLed, its
    stand-in ends by SIGKILL too."""
    argv = ["--standalone", "--nproc-per-node=1", "--no-python", "sleep", "300"]
    sleep = b"sleep\x00300\x00"
    waiting = stand_in("torchrun", argv, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def sleeping() -> int | None:
        return next((pid for pid in procfs.descendants(pool.pid) if procfs.read(pid, "cmdline") == sleep), None)

    sleeper = wait_for(sleeping, "torchrun's worker, below the pool", timeout=120)
    child = int(procfs.stat_fields(sleeper)[1])  # torchrun, forked by the pool
    assert procfs.stat_fields(child)[1] == str(pool.pid)
    try:
        assert os.readlink(f"/proc/{sleeper}/cwd") == str(tmp_path)  # where the stand-in was
        assert b"FTRAIN_TEST_MARK=from-the-stand-in" in procfs.read(sleeper, "environ")  # what it had, via the fork
        os.kill(child, signal.SIGSTOP)
        waiting.kill()
        waiting.wait()
        wait_for(lambda: procfs.stat_fields(child)[:1] in ([], ["Z"]), "the stopped fork to be killed", timeout=10)
    finally:
        os.kill(sleeper, signal.SIGKILL)

    mirror = stand_in("torchrun", argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sleeper = wait_for(sleeping, "the next torchrun's worker", timeout=120)
    try:
        os.kill(int(procfs.stat_fields(sleeper)[1]), signal.SIGKILL)
        assert mirror.wait(timeout=30) == -signal.SIGKILL  # the stand-in ends as its fork did
    finally:
        os.kill(sleeper, signal.SIGKILL)


def test_no_pool_or_a_stranger_means_a_cold_start(pool) -> None:
    """Without a pool for its supervisor the stand-in runs cold at once; the pool closes the connection of another
    user's process (``SO_PEERCRED``) without forking, which a stand-in takes as: run cold."""
    others = child_env({lifeline.SUPERVISOR_ENV: "1:0"})  # a supervisor with no pool
    code = STAND_IN.format(entry="train", argv=["--version"])
    assert subprocess.run([sys.executable, "-c", code], env=others, timeout=60).returncode == COLD
    if os.getuid() != 0 or SYSTEM_PYTHON is None:
        pytest.skip("another user's process needs root and a system python3 (/usr/bin) that any user may run")
    supervisor = lifeline.supervisor_env()[lifeline.SUPERVISOR_ENV]
    own = subprocess.run([SYSTEM_PYTHON, "-c", STRANGER, supervisor], capture_output=True, text=True, timeout=120)
    stranger = subprocess.run(
        [SYSTEM_PYTHON, "-c", STRANGER, supervisor], capture_output=True, text=True, timeout=120, user=NOBODY
    )
    assert (own.stdout, stranger.stdout) == ("forked\n", "refused\n"), (own, stranger)
