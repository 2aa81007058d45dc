"""The exception types that mean "the user gave us bad input" or "the storage failed", the exit codes, and what such a
line is made of: a command it offers (``command``), the word a misspelling meant (``closest``, ``did_you_mean``).

`cli.main` prints their message as a single line and exits with the code that goes with it; everything else is a
bug and keeps its traceback.
"""

import difflib
import errno
import os
import re
import shlex
import signal
import sys
import threading
import time
import traceback
import typing

from ftrain import errorfile
from ftrain.terminal import leave_the_terminal

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
CONTINUE = "run the same command again to continue"
"""What a stopped run's last line tells a person: the same command goes on from the step it saved."""


NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
"""A disk (or the user's quota on it) is full: no retry of the write fixes it, only freeing space does."""


def no_space_line(error: OSError) -> str:
    """One line for a write that found its disk full: which file, and the fix."""
    where = f"for {error.filename}" if error.filename else "on a disk this run writes to (its storage or log directory)"
    fix = "free space there, or keep fewer checkpoints (checkpoint.keep_last); nothing committed is lost"
    return f"no space left {where} ({error.strerror}): {fix}"


def name_too_long_line(error: OSError) -> str:
    """One line for a path with a name longer than its file system takes (bad input, not a failure)."""
    where = error.filename2 or error.filename or "a path this command was given"
    return f"{where}: that path, or a name in it, is longer than its file system takes: use a shorter one"


class Terminated(BaseException):
    """SIGTERM before the command took it over (``stop_on_signals``): a BaseException, as KeyboardInterrupt, so that
    no ``except Exception`` on the way swallows it."""


def stop_on_signals() -> None:
    """From the start of a command until it takes its stop signals over (a run's stop request, the supervisor's), a
    SIGTERM (or SIGHUP) ends it as a Ctrl-C does, in one line (``stopped``) with 143, where it died without a word;
    and every stop, a Ctrl-C too, is remembered (``raise_stop``). Left alone where the process inherited another
    disposition (ignored, say)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for number in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(number) == signal.SIG_DFL:
            signal.signal(number, raise_stop)
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, raise_stop)


def stop_signals() -> tuple[int, ...]:
    """The stop signals a run takes over: SIGTERM; SIGHUP, the terminal or SSH session that closed, a stop like
    SIGTERM (saved, 143); SIGINT. SIGHUP and SIGINT are left ignored where the process started so: ``nohup``, the
    background job of a script, whose Ctrl-C is for the script's foreground (as Python leaves it)."""
    unless_ignored = (signal.SIGHUP, signal.SIGINT)
    return (signal.SIGTERM, *(number for number in unless_ignored if signal.getsignal(number) != signal.SIG_IGN))


def raise_stop(signum: int, frame: object) -> None:
    """Raises a stop's exception (KeyboardInterrupt, ``Terminated``), and remembers the stop: a handler's exception is
    lost where it comes up inside C code that clears errors (a dict lookup that calls a ``__eq__`` of Python's), or in
    an ``except BaseException`` of a library's. Where the command takes its signals over it raises the stop again
    (``raise_lost_stop``)."""
    if signum == signal.SIGHUP:
        leave_the_terminal()
    _received.append(signal.SIGINT if signum == signal.SIGINT else signal.SIGTERM)
    raise KeyboardInterrupt if signum == signal.SIGINT else Terminated


def raise_lost_stop() -> None:
    """Where a command takes its stop signals over (the trainer, torchrun's agent, the supervisor, a warm pool's
    stand-in), and where one that never did ends (``entry.run_command``: ``ckpt ls``): a stop received before and not
    yet said is raised again. A process that got one and is still here lost its exception on the way, as nothing that
    handles a stop before the takeover goes on."""
    if _received:
        first = _received[0]
        _received.clear()
        raise KeyboardInterrupt if first == signal.SIGINT else Terminated


_received: list[int] = []
"""The stops ``raise_stop`` raised (SIGINT, or SIGTERM for a SIGHUP too)."""


def stopped(signum: int) -> int:
    """A stop that came before the command took its signal over (while it imports torch, or in a short command): one
    line instead of a traceback or a silent death, and the shell's code, 128 + the signal. A run saves from the
    moment it took them over. Of a launcher's workers, rank 0 alone says it (``errorfile.says_its_stop``)."""
    said = "interrupted (Ctrl-C)" if signum == signal.SIGINT else f"stopped by {signal.Signals(signum).name}"
    _received.clear()  # handled: not a lost one
    with _SAYING:  # said once, where a launcher's watch (``ftrain.torchrun``) ends a start its main thread could not
        if errorfile.says_its_stop() and not _said:
            _said.append(said)
            print(f"ftrain: {said}", file=sys.stderr, flush=True)
    return 128 + signum


_SAYING = threading.Lock()
_said: list[str] = []


def stop_signal(error: BaseException) -> int | None:
    """The stop signal that caused ``error``, if one did (SIGINT: a KeyboardInterrupt, SIGTERM: ``Terminated``): one
    inside a compiled module's import (MuJoCo's, through pybind11) comes back as an ImportError whose cause it is, and
    the importer may wrap that again."""
    seen = set()
    while error is not None and id(error) not in seen:
        if isinstance(error, KeyboardInterrupt):
            return signal.SIGINT
        if isinstance(error, Terminated):
            return signal.SIGTERM
        seen.add(id(error))
        error = error.__cause__ or error.__context__
    return None


ONE_STOP = 0.5
"""Seconds within which a stop signal of the same number is the same stop delivered again (``Deliveries``)."""


class Deliveries:
    """Tells a stop signal sent again from one stop delivered twice: ``timeout`` passes its signal to the command
    and then to the command's whole process group, a kill of a job's processes may reach one twice; a second Ctrl-C
    by hand comes later. A signal of the number of the one before, within ``ONE_STOP`` seconds, is that one again."""

    def __init__(self) -> None:
        self._last: tuple[int, float] | None = None

    def new(self, signum: int) -> bool:
        """Whether ``signum``, just received, is a stop of its own."""
        now = time.monotonic()
        again = self._last is not None and self._last[0] == signum and now - self._last[1] < ONE_STOP
        self._last = (signum, now)
        return not again


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


def counted(n: int, noun: str) -> str:
    """``n`` and the noun, plural unless one: "1 restart", "0 iterations"."""
    return f"{n} {noun}{'s' * (n != 1)}"


def closest(word: str, known: typing.Iterable[str], cutoff: float = 0.6) -> str | None:
    """The one of ``known`` that ``word`` most likely misspells, for a "did you mean", else None. Case is no
    difference (``ÖNNX``, ``HTTP``); a start of only one of them names it (``unq``), a start of two letters of several
    none (``pl``: play, plot); never the opposite of what was typed (``nodrop-bad`` for ``drop-bad``, ``quarantine``
    for ``unquarantine``), which may do the harm the user avoided."""
    names = {name.casefold(): name for name in known}
    typed = word.casefold()
    starting = [folded for folded in names if typed and folded.startswith(typed)]
    if typed in names or len(starting) == 1:
        near = [typed if typed in names else starting[0]]
    elif len(starting) > 1 and len(typed) < 3:
        return None
    else:
        near = difflib.get_close_matches(typed, names, n=1, cutoff=cutoff)
    return names[near[0]] if near and not _negates(typed, near[0]) else None


def did_you_mean(word: str, known: typing.Iterable[str]) -> str:
    """`` (did you mean X?)`` where ``word`` is close to one X of ``known`` (``closest``), else nothing."""
    near = closest(word, known)
    return f" (did you mean {near}?)" if near else ""


def _negates(typed: str, known: str) -> bool:
    """Whether one is (close to) the other with a negation before it, however it is joined (``no_drop_bad``,
    ``nodropbad``; ``quarantin`` for ``unquarantine``)."""
    one, other = (re.sub("[-_]", "", word) for word in (typed, known))
    return any(
        negated.startswith(negation)
        and not plain.startswith(negation)
        and negated[len(negation) : len(negation) + 1] == plain[:1]  # ``noderank`` for ``oderank`` is a typo
        and difflib.SequenceMatcher(None, negated[len(negation) :], plain).ratio() >= 0.8
        for negated, plain in ((one, other), (other, one))
        for negation in ("dont", "non", "not", "no", "un")
    )


def module_missing(error: BaseException, name: str) -> bool:
    """Whether importing module ``name`` failed because it (or a package above it) is not there, as opposed to its
    own code failing, an import of its own included."""
    missing = getattr(error, "name", None) if isinstance(error, ModuleNotFoundError) else None
    return bool(missing) and f"{name}.".startswith(f"{missing}.")


def error_line(error: BaseException) -> str:
    """An exception in one line, with where it was raised: ``Type: message (file, line N)``."""
    text = " ".join(f"{type(error).__name__}: {error}".split())
    frames = traceback.extract_tb(error.__traceback__)
    if frames and not isinstance(error, SyntaxError) and not frames[-1].filename.startswith("<"):
        # a SyntaxError names its file and line itself; importlib's own frames (<frozen ...>) tell nothing
        text += f" ({short_path(frames[-1].filename)}, line {frames[-1].lineno})"
    return text


def short_path(path: str) -> str:
    """``path`` relative to the working directory where it lies below it, else as it is."""
    relative = os.path.relpath(path)
    return path if relative.startswith("..") else relative


SIZE_MISMATCH = re.compile(
    r"size mismatch for ([\w.]+): copying a param with shape torch\.Size\(\[([\d, ]*)\]\) from checkpoint, the shape "
    r"in current model is torch\.Size\(\[([\d, ]*)\]\)"
)
"""torch's words for a tensor of a checkpoint whose shape is not the model's (``load_state_dict``)."""


OBSERVATION_SIZED = ("obs_normalizer._mean", "mlp.0.weight")
"""Tensors of rsl-rl's models whose last dimension is the observation's size; ``ACTION_SIZED``: the action's."""
ACTION_SIZED = ("distribution.std_param", "distribution.log_std_param")


def load_error_line(error: BaseException) -> str:
    """Why a checkpoint's state did not load into a model, in one line: the sizes of observations and actions where
    they differ, the first tensor whose shape differs and how many more do, else the error's first 300 characters
    (torch's account of a shape lists every tensor, pages of it)."""
    found = SIZE_MISMATCH.findall(str(error))
    if not found:
        return f"{type(error).__name__}: {' '.join(str(error).split())[:300]}"
    key, saved, now = found[0]
    more = f", and {len(found) - 1} more tensors" if len(found) > 1 else ""
    line = f"{key} is [{saved}] in the checkpoint but [{now}] in the model built now{more}"
    sizes = {name: (int(saved.split(",")[-1]), int(now.split(",")[-1])) for name, saved, now in found}
    observations = next((sizes[name] for name in sizes if name.endswith(OBSERVATION_SIZED)), None)
    actions = next((sizes[name] for name in sizes if name.endswith(ACTION_SIZED)), None)
    said = [f"it takes {observations[0]} observations, the env gives {observations[1]}"] if observations else []
    said += [f"it gives {actions[0]} actions, the env takes {actions[1]}"] if actions else []
    return f"{'; '.join(said)} ({line})" if said else line
