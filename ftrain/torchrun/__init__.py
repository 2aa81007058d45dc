"""torchrun with ftrain's exit codes: ``python -m ftrain.torchrun [--failures=FILE] <torchrun arguments>``.

This is torchrun itself, in this process, except for how it ends. Stopped by a signal (SIGINT, SIGTERM), it stops the
workers with it (torchrun's own shutdown: they save) and exits 128 + the signal (130, 143) where torchrun would raise
and exit 1; when every worker that ended exited 130 or 143 (they were stopped and saved), it exits with that code. So
a script tells a stop from a failure, which plain ``torchrun`` (exit 1 for both) does not let it. Where a worker
explained its failure itself (bad input, a storage that does not answer: ``errorfile.report``) and that was the first
failure, it exits with the worker's code after that one line (printed by rank 0, else here), without torchrun's
report of the failure or its log lines about it; a crash keeps torchrun's report, with the worker's traceback. An
elastic launch (``--nnodes MIN:MAX``) tells its workers MIN and MAX (``config.ELASTIC_NODES_ENV``), so that they refuse
at the start a total of environments that a world of the launch could not share. This is what the docs show for a run
without a supervisor; ``ftrun`` is the same command.

``ftrain supervise`` runs it with ``--failures=FILE``: instead of raising ChildFailedError (a traceback and a text
report on stderr), it writes torchrun's own account of every failed worker to FILE, as JSON ``{global rank:
{"exitcode": code, "error": the JSON of its error file or null}}`` (a negative code: killed by that signal; the error
file: what the worker recorded, see ``ftrain/errorfile.py``), and exits 1 (or 130, 143, as above). An elastic
rendezvous that did not gather its minimum of nodes in time is one line on stderr and exit ``EXIT_RENDEZVOUS_TIMEOUT``:
not a failure to restart, a lack of nodes. It ends with its supervisor, however that ends (``ftrain/lifeline.py``).

The agent is ``agent.py``; this package's top is the command (``console``), which imports it inside the stop guard of
``ftrain/entry.py``. May import: config, entry, errors, errorfile, files, lifeline, process, proctitle, terminal.
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
