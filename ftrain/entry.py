"""Where every command starts (``ftrain``, ``ftrun``, and ``python -m`` of ``ftrain`` or ``ftrain.torchrun``): a stop
at any moment of it is one line.

A Ctrl-C, SIGTERM or SIGHUP while a command imports (torch takes seconds on a slow machine), and until the command
takes its signals over, ends it with ``ftrain: interrupted (Ctrl-C)`` or ``ftrain: stopped by SIGTERM`` and 128 + the
signal (``errors.stopped``), where Python would print a traceback or die without a word. So the entries import
nothing at their top but this module, which itself imports nothing at its top: what comes before it is the
interpreter's own start, and the package's ``__init__`` (a millisecond). It imports the rest inside the guard: an
import a stop cut short leaves nothing in ``sys.modules``, so ``errors`` imports whole in the handler.
"""

from __future__ import annotations

TYPE_CHECKING = False  # not typing's: its import would take longer than this module's
if TYPE_CHECKING:
    from collections.abc import Callable
    from typing import NoReturn


def run_command(start: Callable[[], int | None]) -> NoReturn:
    """Runs ``start``, which imports what its command needs, and exits with its code, or with a stop's one line,
    without the interpreter's teardown (``process.exit_fast``): also so that the code is the one given, as a stop
    inside ``exec`` of a string (dataclasses make their methods so) leaves CPython 3.11 marked for an unhandled Ctrl-C,
    and its normal exit would end by SIGINT after the one line. A crash, and ``sys.exit``, end as Python ends them."""
    try:
        from ftrain.errors import raise_lost_stop, stop_on_signals
        from ftrain.process import exit_fast
        from ftrain.terminal import outlive_a_hangup

        outlive_a_hangup()  # first: a SIGHUP's line must not fail on the terminal that hung up
        stop_on_signals()
        code = start()
        raise_lost_stop()  # a short command that never took its signals over (``ckpt ls``) may have lost one too
        exit_fast(code)
    except SystemExit:
        raise
    except BaseException as error:
        import signal

        for number in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # a second stop would cut this one's line
            signal.signal(number, signal.SIG_IGN)
        from ftrain.errors import stop_signal, stopped
        from ftrain.process import exit_fast

        if (signum := stop_signal(error)) is None:
            raise
        exit_fast(stopped(signum))
