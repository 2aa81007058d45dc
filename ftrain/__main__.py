"""``ftrain`` and ``python -m ftrain`` (``torchrun -m ftrain`` too): a worker of a supervisor with a warm pool runs
there (see ``ftrain/warm``). It imports inside the stop guard of ``ftrain/entry.py``: a Ctrl-C or SIGTERM while it
imports is one line, not a traceback or a silent death; and it ends without the interpreter's teardown, as a fork of
the pool does."""

from __future__ import annotations

import sys

from ftrain.entry import run_command

TYPE_CHECKING = False  # not typing's, as in ``ftrain/entry.py``
if TYPE_CHECKING:
    from typing import NoReturn


def main() -> NoReturn:
    run_command(_command)


def _command() -> int:
    from ftrain.proctitle import name_process, rank_role
    from ftrain.warm import handover

    if sys.argv[1:2] == ["train"]:
        name_process(rank_role("stand-in"))  # a worker forked by the pool names itself once it knows its run
        code = handover("train", sys.argv[1:])
        if code is not None:
            return code
    from ftrain.cli import main

    return main()


if __name__ == "__main__":
    main()
