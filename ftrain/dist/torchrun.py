"""torchrun as ``ftrain supervise`` runs it: ``python -m ftrain.dist.torchrun FAILURES <torchrun arguments>``.

This is torchrun itself, in this process, except for how it ends when workers fail: instead of raising
ChildFailedError (a traceback and a text report on stderr), it writes torchrun's own account of every failed worker
to FAILURES, as JSON ``{global rank: {"exitcode": code, "error": the JSON of its error file or null}}`` (a negative
code: killed by that signal; the error file: what the worker recorded, see ``ftrain/errorfile.py``), and exits 1, or
130 or 143 when every worker that ended exited so (they were stopped by SIGINT or SIGTERM and saved). Stopped itself by
a signal (SIGINT, SIGTERM), it stops the workers with it (torchrun's own shutdown: they save) and exits 128 + the signal
(130, 143), where torchrun would raise.
An elastic rendezvous that did not gather its minimum of nodes in time is one line on stderr and exit
``EXIT_RENDEZVOUS_TIMEOUT``: not a failure to restart, a lack of nodes. It ends with its supervisor, however that
ends (``ftrain/lifeline.py``).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from torch.distributed.elastic.multiprocessing.api import SignalException
from torch.distributed.elastic.multiprocessing.errors import ChildFailedError
from torch.distributed.elastic.rendezvous.api import RendezvousTimeoutError
from torch.distributed.run import main as torchrun

from ftrain.errors import EXIT_RENDEZVOUS_TIMEOUT, STOPPED
from ftrain.lifeline import die_with_supervisor

EXIT_WORKERS_FAILED = 1


def main(argv: list[str]) -> int:
    die_with_supervisor()
    failures_path, *arguments = argv
    try:
        torchrun(arguments)
    except ChildFailedError as failed:
        failures = {
            rank: {"exitcode": failure.exitcode, "error": _recorded(failure.error_file, failure.error_file_data)}
            for rank, failure in failed.failures.items()
        }
        path = Path(failures_path)
        path.with_suffix(".tmp").write_text(json.dumps(failures))
        os.replace(path.with_suffix(".tmp"), path)
        codes = {failure.exitcode for failure in failed.failures.values()}
        return codes.pop() if len(codes) == 1 and codes <= set(STOPPED) else EXIT_WORKERS_FAILED
    except SignalException as stopped:  # the agent has stopped the workers with the same signal before raising
        return 128 + int(stopped.sigval)
    except RendezvousTimeoutError as error:
        print(f"torchrun: rendezvous timed out: {' '.join(str(error).split())}", file=sys.stderr, flush=True)
        return EXIT_RENDEZVOUS_TIMEOUT
    return 0


def _recorded(error_file: str, data: dict) -> dict | None:
    """What the worker wrote to its error file (torchrun names a missing one ``<N/A>``)."""
    return data if os.path.isfile(error_file) else None


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
