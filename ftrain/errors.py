"""The exception types that mean "the user gave us bad input" or "the storage failed", and the exit codes.

`cli.main` prints their message as a single line and exits with the code that goes with it; everything else is a
bug and keeps its traceback.
"""

import errno
import shlex
import signal
import sys

EXIT_FAILED = 1
"""A storage operation failed for good (``StorageError``) outside training."""
EXIT_USAGE = 2
EXIT_STORAGE_DOWN = 7
"""A worker, and ``ftrain supervise`` after ``--storage-wait``: the checkpoint storage did not answer. Not bad input and
nothing lost: the supervisor waits for the storage and starts again; run the same command again once it is back."""
EXIT_RENDEZVOUS_TIMEOUT = 6
"""torchrun (``ftrain.torchrun``) and ``ftrain supervise``: an elastic rendezvous did not gather its minimum of
nodes in time."""
EXIT_STORAGE_HELD = 8
"""``ftrain supervise`` and ``ftrain train`` (every rank): another run, alive, holds the storage's lease
(``ftrain.ckpt.lease``); nothing of that run is touched."""
EXIT_PREEMPTED = 128 + signal.SIGTERM
"""Stopped by SIGTERM after saving (workers, torchrun as the supervisor runs it, ``ftrain supervise``): 128 + the
signal, as a shell reports it, so that schedulers that retry signal exits run it again."""
EXIT_INTERRUPTED = 128 + signal.SIGINT
"""Stopped by SIGINT (Ctrl-C) after saving: the same as ``EXIT_PREEMPTED``, with the shell's code for Ctrl-C."""
STOPPED = (EXIT_PREEMPTED, EXIT_INTERRUPTED)
"""The exit codes of a run stopped by a signal after saving."""


NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
"""A disk (or the user's quota on it) is full: no retry of the write fixes it, only freeing space does."""


def no_space_line(error: OSError) -> str:
    """One line for a write that found its disk full: which file, and the fix."""
    where = f"for {error.filename}" if error.filename else "on a disk this run writes to (its storage or log directory)"
    fix = "free space there, or keep fewer checkpoints (checkpoint.keep_last); nothing committed is lost"
    return f"no space left {where} ({error.strerror}): {fix}"


def interrupted() -> int:
    """A Ctrl-C that came before the command took SIGINT over (while it imports torch, or in a short command): one
    line instead of a traceback, and the shell's code for Ctrl-C. A run saves from the moment it took it over."""
    print("ftrain: interrupted (Ctrl-C)", file=sys.stderr, flush=True)
    return EXIT_INTERRUPTED


def stop_code(signum: int) -> int:
    """The exit code after a stop by ``signum``: 128 + the signal, as a shell reports it (130 for Ctrl-C)."""
    return EXIT_INTERRUPTED if signum == signal.SIGINT else EXIT_PREEMPTED


class UserError(Exception):
    """Bad input: the message names the input and the fix, and fits on one line."""


class StorageError(Exception):
    """A storage operation failed for good (after retrying when the cause looked transient)."""


class StorageUnavailable(StorageError):
    """The storage did not answer, or answered busy, through every retry: wait for it (never bad input)."""


def command(*words: object) -> str:
    """A command line for a user to paste, each word shell-quoted where it needs to be (a path with a space)."""
    return " ".join(shlex.quote(str(word)) for word in words)
