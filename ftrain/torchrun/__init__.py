"""torchrun with ftrain's exit codes: ``python -m ftrain.torchrun [--failures=FILE] <torchrun arguments>`` (``ftrun``).

This is torchrun itself, in this process, except for how it ends, so that a script tells a stop from a failure (plain
``torchrun`` exits 1 for both): a stop (SIGINT, SIGTERM) stops the workers (they save) and exits 128 + the signal; a
failure a worker explained (bad input, a storage that does not answer) is that one line and the worker's code; a
crash keeps torchrun's report. ``ftrain supervise`` passes ``--failures=FILE``, where torchrun's account of each
failed worker goes instead of a traceback; an elastic rendezvous short of its nodes is one line and
``EXIT_RENDEZVOUS_TIMEOUT``. The details are the agent's (``agent.py``); this package's top is the command
(``console``), which imports it inside the stop guard of ``ftrain/entry.py``.
May import: config, entry, errors, errorfile, files, lifeline, process, proctitle, terminal.
"""

from __future__ import annotations

import sys

from ftrain.entry import run_command

TYPE_CHECKING = False  # not typing's, as in ``ftrain/entry.py``
if TYPE_CHECKING:
    from typing import NoReturn


def console() -> NoReturn:
    """``ftrun`` and ``python -m ftrain.torchrun``: a stop before torchrun takes the signals over (while torch
    imports, or in the rendezvous) is one line and 128 + the signal, not a traceback or a silent death."""
    run_command(_agent)


def _agent() -> int:
    from ftrain.torchrun.agent import main

    return main(sys.argv[1:])
