"""torchrun's agent in this process (``run``), ending as ``ftrain.torchrun`` promises.

- Stopped by a signal, it stops the workers with torchrun's own shutdown (they save) and exits 128 + the signal where
  torchrun would raise and exit 1; when every worker that ended exited 130 or 143 (stopped and saved), with that code.
- Where a worker explained its failure itself (``errorfile.report``) and that was the first failure, it exits with the
  worker's code after that one line (printed by rank 0, else here), without torchrun's report or its log lines about
  it; a crash keeps torchrun's report, with the worker's traceback.
- With ``--failures=FILE`` (``ftrain supervise``), instead of raising ChildFailedError it writes torchrun's account of
  every failed worker to FILE as JSON ``{global rank: {"exitcode": code, "error": its error file's JSON or null}}``
  (a negative code: killed by that signal) and exits 1 (or 130, 143, as above).
- An elastic rendezvous that did not gather its minimum of nodes in time is one line and ``EXIT_RENDEZVOUS_TIMEOUT``:
  a lack of nodes, not a failure to restart. An elastic launch (``--nnodes MIN:MAX``) tells its workers MIN and MAX
  (``config.ELASTIC_NODES_ENV``), so that they refuse at the start a total of environments a world could not share.
- It ends with its supervisor, however that ends (``ftrain/lifeline.py``).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import sys
import threading
import time
import typing

if typing.TYPE_CHECKING:
    from torch.distributed.elastic.multiprocessing.errors import ChildFailedError

from ftrain import errorfile
from ftrain.config import ELASTIC_NODES_ENV
from ftrain.errors import (
    EXIT_RENDEZVOUS_TIMEOUT,
    STOPPED,
    raise_lost_stop,
    stop_code,
    stop_signals,
    stopped,
)
from ftrain.files import replace_text
from ftrain.lifeline import die_with_supervisor
from ftrain.process import imports
from ftrain.proctitle import AGENT, name_process
from ftrain.terminal import outlive_a_hangup

EXIT_WORKERS_FAILED = 1
FAILURES_OPTION = "--failures="
STOP_GRACE = 1.0
"""Seconds a stop before the workers start has for its own handler to end the process, before the watch ends it."""
QUIETED = {
    "torch.distributed.run": ("Setting OMP_NUM_THREADS",),  # ftrain sets each worker's threads itself (torch_threads)
    "torch.distributed.elastic.multiprocessing.api": ("failed (exitcode", "closing signal"),  # the end says it
    "torch.distributed.elastic.agent.server.api": ("death signal",),  # the workers' and the agent's lines say it
    "torch.distributed.elastic.multiprocessing.errors.error_handler": ("no error file defined for parent",),
}
"""torchrun's log lines that a run by hand does without: logger, and fragments of the lines."""


def main(argv: list[str]) -> int:
    die_with_supervisor()
    return run(argv)


def run(argv: list[str]) -> int:
    """torchrun in this process: ``main`` without the tie to the supervisor (the warm pool forks it: ``ftrain/warm``,
    where it ends with the pool)."""
    name_process(AGENT)
    outlive_a_hangup()
    # the agent's own handlers: the stop signals this process takes (a SIGHUP ignored under nohup stays so), SIGQUIT
    os.environ.setdefault(
        "TORCHELASTIC_SIGNALS_TO_HANDLE",
        ",".join(sig.name for sig in map(signal.Signals, (*stop_signals(), signal.SIGQUIT))),
    )
    with imports():  # here, not at the top: a Ctrl-C meanwhile is the one line of ``console``
        from torch.distributed.elastic.multiprocessing.api import SignalException
        from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
        from torch.distributed.elastic.rendezvous.api import RendezvousTimeoutError
        from torch.distributed.run import main as torchrun
    failures_path = argv[0].removeprefix(FAILURES_OPTION) if argv[:1] and argv[0].startswith(FAILURES_OPTION) else None
    arguments = argv[1:] if failures_path is not None else argv
    if failures_path is None:
        _quiet_torchrun()
    _tell_workers_the_nodes(arguments)
    raise_lost_stop()  # before torchrun takes the signals over
    _watch_for_a_stop_before_the_workers()
    try:
        torchrun(arguments)
    except ChildFailedError as failed:
        codes = {failure.exitcode for failure in failed.failures.values()}
        stopped = codes.pop() if len(codes) == 1 and codes <= set(STOPPED) else None
        if failures_path is None:
            if stopped is not None:
                print(f"torchrun: the workers stopped by a signal, exit {stopped}", file=sys.stderr)
                return stopped
            explained = _explained(failed)
            if explained is None:
                raise  # torchrun's own report of the failure
            return explained
        failures = {
            rank: {"exitcode": failure.exitcode, "error": _recorded(failure.error_file, failure.error_file_data)}
            for rank, failure in failed.failures.items()
        }
        replace_text(failures_path, json.dumps(failures))
        return stopped or EXIT_WORKERS_FAILED
    except SignalException as signalled:  # the agent has stopped the workers with the same signal before raising
        return stop_code(int(signalled.sigval)) if signalled.sigval in stop_signals() else 128 + int(signalled.sigval)
    except RendezvousTimeoutError as error:
        print(f"torchrun: rendezvous timed out: {' '.join(str(error).split())}", file=sys.stderr, flush=True)
        return EXIT_RENDEZVOUS_TIMEOUT
    return 0


def _watch_for_a_stop_before_the_workers() -> None:
    """Ctrl-C, SIGTERM or SIGHUP while torchrun waits for its rendezvous: torch's TCPStore retries its connect
    through the interruption (up to 15 minutes, a C++ trace each time), so Python's handler, which runs only once that
    call returns, never ran. A thread woken by the signal itself (``signal.set_wakeup_fd``) ends the process with the
    stop's one line where, a second later, it has not ended and no worker has started (the agent takes the signals
    over when it starts them): there is nothing to save."""
    if threading.current_thread() is not threading.main_thread():
        return
    ours = {number: signal.getsignal(number) for number in stop_signals()}
    readable, writable = os.pipe()
    os.set_blocking(writable, False)
    signal.set_wakeup_fd(writable, warn_on_full_buffer=False)

    def watch() -> None:
        while True:
            signum = os.read(readable, 1)[0]
            if signum in ours:
                time.sleep(STOP_GRACE)
                if signal.getsignal(signum) is ours[signum]:
                    os._exit(stopped(signal.SIGTERM if signum == signal.SIGHUP else signum))

    threading.Thread(target=watch, name="stop before the workers", daemon=True).start()


def _explained(failed: ChildFailedError) -> int | None:
    """The first failure's exit code where its worker explained it in one line (printed here unless rank 0 printed
    the same line: only rank 0 prints its own); None where the first failure is a crash or left no account."""
    recorded = {
        rank: _recorded(failure.error_file, failure.error_file_data) for rank, failure in failed.failures.items()
    }
    first = min(recorded, key=lambda rank: errorfile.recorded_at(recorded[rank]))
    if not errorfile.reported(recorded[first]):
        return None
    line = errorfile.message(recorded[first])
    said = recorded.get(0)
    if not (errorfile.reported(said) and errorfile.message(said) == line):
        print(f"ftrain: error: {line}", file=sys.stderr, flush=True)
    return failed.failures[first].exitcode


def _tell_workers_the_nodes(arguments: list[str]) -> None:
    """An elastic launch's ``--nnodes MIN:MAX`` in the workers' environment (``ELASTIC_NODES_ENV``): a world size of
    the launch that cannot share the run's environments is refused at the start (``config.for_launch``)."""
    from torch.distributed.run import get_args_parser, parse_min_max_nnodes

    os.environ.pop(ELASTIC_NODES_ENV, None)  # not one inherited from another launch
    parser = get_args_parser()
    parser.error = _unparsed  # torchrun itself says what is wrong with its arguments
    try:
        least, most = parse_min_max_nnodes(parser.parse_args(arguments).nnodes)
    except (RuntimeError, ValueError):
        return
    if least < most:
        os.environ[ELASTIC_NODES_ENV] = f"{least}:{most}"


def _unparsed(message: str) -> typing.NoReturn:
    raise ValueError(message)


def _quiet_torchrun() -> None:
    for name, fragments in QUIETED.items():
        logging.getLogger(name).addFilter(
            lambda record, fragments=fragments: not any(fragment in str(record.msg) for fragment in fragments)
        )


def _recorded(error_file: str, data: dict) -> dict | None:
    """What the worker wrote to its error file (torchrun names a missing one ``<N/A>``)."""
    return data if os.path.isfile(error_file) else None
