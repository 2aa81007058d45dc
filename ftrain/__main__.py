"""``python -m ftrain`` and ``torchrun -m ftrain``: a worker of a supervisor with a warm pool runs there (see
``ftrain/warm``). Every command ends without the interpreter's teardown (``ftrain/process.py``), as a fork of the pool
does. A Ctrl-C or SIGTERM while it imports is one line (``errors.stopped``), not a traceback or a silent death."""

import sys

from ftrain.errors import Terminated, stop_on_sigterm, stop_signal, stopped

stop_on_sigterm()
try:
    from ftrain.process import exit_fast
    from ftrain.proctitle import name_process, rank_role
    from ftrain.warm import handover

    if sys.argv[1:2] == ["train"]:
        name_process(rank_role("stand-in"))  # a worker forked by the pool names itself once it knows its run
    code = handover("train", sys.argv[1:]) if sys.argv[1:2] == ["train"] else None
    if code is None:
        from ftrain.cli import main

        code = main()
except (KeyboardInterrupt, Terminated, Exception) as error:
    if (signum := stop_signal(error)) is None:
        raise
    sys.exit(stopped(signum))
exit_fast(code)
