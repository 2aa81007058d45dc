"""``ftrain/process.py``: imports without the garbage collector, and an exit without the interpreter's teardown that
still loses nothing: in real child processes, whose output goes to a pipe (buffered, as under torchrun)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

from helpers import REPO, child_env

CHILD = textwrap.dedent(
    """
    import atexit, ctypes, gc, sys, threading, time
    from ftrain.process import exit_fast, imports

    gc.disable() if sys.argv[1] == "gc-off" else None
    was = gc.isenabled()
    with imports():
        assert not gc.isenabled()
        import json.decoder
    assert gc.isenabled() == was and gc.get_freeze_count() > 0, (gc.isenabled(), gc.get_freeze_count())
    atexit.register(lambda: print("atexit ran"))
    threading.Thread(target=lambda: (time.sleep(0.3), print("thread finished"))).start()
    print("python line")
    ctypes.CDLL(None).printf(b"C line\\n")
    exit_fast(3, None if sys.argv[2] == "code" else 2)
    """
)


def run_child(gc_state: str, ending: str) -> subprocess.CompletedProcess:
    env = child_env()
    env.pop("PYTHONUNBUFFERED", None)  # buffered, as Python's and C's streams are by default on a pipe
    return subprocess.run([sys.executable, "-c", CHILD, gc_state, ending], cwd=REPO, env=env, capture_output=True)


def test_an_exit_without_teardown_keeps_the_exit_code_and_loses_no_output_thread_or_exit_function():
    result = run_child("gc-on", "code")
    assert result.returncode == 3, result.stderr.decode()
    lines = result.stdout.decode().splitlines()  # C's buffer and Python's reach the pipe each in one piece
    assert [line for line in lines if line != "C line"] == ["python line", "thread finished", "atexit ran"], result
    assert "C line" in lines
    assert result.stderr == b""


def test_an_exit_by_signal_ends_by_it_and_imports_leave_a_disabled_collector_disabled():
    result = run_child("gc-off", "signal")
    assert result.returncode == -signal.SIGINT, result.stderr.decode()
    assert b"python line" in result.stdout and b"C line" in result.stdout
