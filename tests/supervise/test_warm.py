"""The warm pool (``ftrain/warm``) on its own: a real pool process, started by the supervisor's ``Launcher`` in
this test process (its supervisor), and real stand-ins that hand their command over to it. Supervised runs use it by
default: every test of ``ftrain supervise`` with the real trainer goes through it, and ``test_chaos.py`` compares
them with cold runs."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys

import pytest

from ftrain import lifeline, procfs
from ftrain.supervise.attempt import Launcher
from ftrain.supervise.options import SupervisorOptions
from ftrain.warm import POOL_ENV, address

from helpers import REPO, child_env, wait_for

NOBODY = 65534
STAND_IN = "import sys; from ftrain.warm import handover; code = handover({entry!r}, {argv!r}); sys.exit(code)"
"""A stand-in: exit status None (0) when no pool took its command (it would then run it cold)."""
COLD = 0
STRANGER = """
import json, socket, struct, sys
connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
connection.connect("\\0ftrain-warm-" + sys.argv[1].replace(":", "-"))
request = {"secret": sys.argv[2], "entry": "train", "argv": ["train"], "sys_argv": ["ftrain"], "env": {}, "cwd": "/"}
request["umask"] = 18
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
def pool(tmp_path):
    """A warm pool whose supervisor is this test process, and what its stand-ins' environment needs."""
    launcher = Launcher(SupervisorOptions(), tmp_path / "pool.log")
    assert launcher.pool is not None, (tmp_path / "pool.log").read_text()
    yield launcher.pool, launcher.command([], [], tmp_path)[1]
    launcher.close()


def stand_in(pool: tuple, entry: str, argv: list[str], **popen: object) -> subprocess.Popen:
    code = STAND_IN.format(entry=entry, argv=argv)
    env = child_env({**lifeline.supervisor_env(), **pool[1], "FTRAIN_TEST_MARK": "from-the-stand-in"})
    return subprocess.Popen([sys.executable, "-c", code], cwd=popen.pop("cwd", REPO), env=env, **popen)


@pytest.mark.slow  # a warm pool: imports torch, MuJoCo and rsl-rl
def test_the_pool_runs_the_command_with_the_stand_ins_streams_directory_environment_and_exit_code(pool, tmp_path):
    """``ftrain --version`` exits 0 by SystemExit after printing to the stand-in's stdout; a usage error exits 2 with
    its one line on the stand-in's stderr."""
    version = stand_in(pool, "train", ["--version"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path)
    out, err = version.communicate(timeout=120)
    assert version.returncode == 0 and out.decode().startswith("ftrain "), (out, err)

    wrong = stand_in(pool, "train", ["train"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = wrong.communicate(timeout=60)
    assert wrong.returncode == 2 and b"error: the following arguments are required: config: see ftrain train" in err, (
        out,
        err,
    )


@pytest.mark.slow  # a warm pool: imports torch, MuJoCo and rsl-rl
def test_the_fork_lives_in_the_stand_ins_directory_and_environment_and_dies_with_it(pool, tmp_path):
    """A fork that runs (here torchrun's stand-in for a worker that sleeps) sees the stand-in's working directory
    and environment; SIGSTOPped and then left by its SIGKILLed stand-in, the pool SIGKILLs it; SIGKILLed, its
    stand-in ends by SIGKILL too."""
    argv = ["--standalone", "--nproc-per-node=1", "--no-python", "sleep", "300"]
    sleep = b"sleep\x00300\x00"
    waiting = stand_in(pool, "torchrun", argv, cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def sleeping() -> int | None:
        return next((pid for pid in procfs.descendants(pool[0].pid) if procfs.read(pid, "cmdline") == sleep), None)

    sleeper = wait_for(sleeping, "torchrun's worker, below the pool", timeout=120)
    child = int(procfs.stat_fields(sleeper)[1])  # torchrun, forked by the pool
    assert procfs.stat_fields(child)[1] == str(pool[0].pid)
    try:
        assert os.readlink(f"/proc/{sleeper}/cwd") == str(tmp_path)  # where the stand-in was
        assert b"FTRAIN_TEST_MARK=from-the-stand-in" in procfs.read(sleeper, "environ")  # what it had, via the fork
        os.kill(child, signal.SIGSTOP)
        waiting.kill()
        waiting.wait()
        wait_for(lambda: procfs.stat_fields(child)[:1] in ([], ["Z"]), "the stopped fork to be killed", timeout=10)
    finally:
        os.kill(sleeper, signal.SIGKILL)

    mirror = stand_in(pool, "torchrun", argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    sleeper = wait_for(sleeping, "the next torchrun's worker", timeout=120)
    try:
        os.kill(int(procfs.stat_fields(sleeper)[1]), signal.SIGKILL)
        assert mirror.wait(timeout=30) == -signal.SIGKILL  # the stand-in ends as its fork did
    finally:
        os.kill(sleeper, signal.SIGKILL)


@pytest.mark.slow  # a warm pool: imports torch, MuJoCo and rsl-rl
def test_no_pool_a_stranger_or_a_wrong_secret_means_a_cold_start(pool) -> None:
    """Without a pool the stand-in runs cold at once; the pool closes the connection of another user's process
    (``SO_PEERCRED``), or of one without the secret, without forking, which a stand-in takes as: run cold."""
    code = STAND_IN.format(entry="train", argv=["--version"])
    assert subprocess.run([sys.executable, "-c", code], env=child_env(), timeout=60).returncode == COLD
    if os.getuid() != 0 or SYSTEM_PYTHON is None:
        pytest.skip("another user's process needs root and a system python3 (/usr/bin) that any user may run")
    supervisor = lifeline.supervisor_env()[lifeline.SUPERVISOR_ENV]
    secret = pool[1][POOL_ENV]

    def ask(secret: str, **popen: object) -> str:
        command = [SYSTEM_PYTHON, "-c", STRANGER, supervisor, secret]
        return subprocess.run(command, capture_output=True, text=True, timeout=120, **popen).stdout

    assert (ask(secret), ask("a guess"), ask(secret, user=NOBODY)) == ("forked\n", "refused\n", "refused\n")


def test_a_socket_name_taken_by_someone_else_means_cold_starts(tmp_path, capfd) -> None:
    """Whoever binds the pool's name first (anyone may: it can be guessed) gets no stand-in's request: the
    supervisor starts no pool, says so, and its attempts start cold."""
    squatter = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    squatter.bind(address(lifeline.supervisor_env()[lifeline.SUPERVISOR_ENV]))
    with squatter:
        launcher = Launcher(SupervisorOptions(), tmp_path / "pool.log")
    command, env = launcher.command([], [], tmp_path)
    assert launcher.pool is None and env == {} and "ftrain.torchrun" in command
    assert "ftrain supervise: no warm pool ([Errno 98] Address already in use): cold starts" in capfd.readouterr().err
