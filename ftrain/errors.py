"""The one exception type that means "the user gave us bad input".

`cli.main` prints its message as a single line and exits with `EXIT_USAGE`; everything else is a bug
and keeps its traceback.
"""

EXIT_USAGE = 2
EXIT_STORAGE_DOWN = 7
"""A worker, and ``ftrain supervise`` after ``--storage-wait``: the checkpoint storage did not answer. Not bad input and
nothing lost: the supervisor waits for the storage and starts again; run the same command again once it is back."""
EXIT_RENDEZVOUS_TIMEOUT = 6
"""torchrun (``ftrain.dist.torchrun``) and ``ftrain supervise``: an elastic rendezvous did not gather its minimum of
nodes in time."""
EXIT_STORAGE_HELD = 8
"""``ftrain supervise`` and ``ftrain train`` (every rank): another run, alive, holds the storage's lease
(``ftrain.ckpt.lease``); nothing of that run is touched."""


class UserError(Exception):
    """Bad input: the message names the input and the fix, and fits on one line."""
