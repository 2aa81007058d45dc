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


def test_a_ctrl_c_during_the_imports_is_raised_once_they_are_done_and_only_then() -> None:
    """Raised inside an import, a KeyboardInterrupt can come out as the library's ImportError or be swallowed by an
    optional import's ``except ImportError``: a real SIGINT inside the block reaches the code after it, once; the
    handler before is back, and one installed by the code (the trainer's) is left alone."""
    child = textwrap.dedent(
        """
        import os, signal, time
        from ftrain.process import imports

        try:
            with imports():
                os.kill(os.getpid(), signal.SIGINT)
                try:
                    time.sleep(0.2)  # where a library's import would run on
                except ImportError:  # as an optional import's guard
                    print("swallowed")
                print("imports done")
        except KeyboardInterrupt:
            print("interrupted after them")
        print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)
        signal.signal(signal.SIGINT, lambda signum, frame: print("own handler"))
        with imports():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.2)
        print("no hold over a handler of the code's")
        """
    )
    result = subprocess.run([sys.executable, "-c", child], cwd=REPO, env=child_env(), capture_output=True, text=True)
    said = ["imports done", "interrupted after them", "True", "own handler", "no hold over a handler of the code's"]
    assert result.stdout.splitlines() == said, result.stderr
