"""The user's code a run needs, checked before anything is taken (a lease, a log directory, a rendezvous): the env
(``ftrain.policy.robot.check_env``: its module imported, its id registered, its model compiled, its spaces flat, a
first reset and step with its ``kwargs``), then its hooks (``hooks.hook_class``: modules, classes and kwargs), which
the env's ``imports`` may be what they need, and the packages of the trackers turned on (rank 0's, who tracks: an
install that raises on import). Whatever fails is a UserError of one line.

``ftrain train`` calls ``check`` in its own process; ``ftrain supervise`` runs ``python -m ftrain.train.user_code``
in a child with the config's JSON on stdin (``ftrain.supervise.user_check``), which prints the line on stderr and
exits 2.
"""

from __future__ import annotations

import importlib
import json
import sys
from collections.abc import Sequence

from ftrain.config import EnvConfig, HookConfig
from ftrain.errors import UserError, error_line
from ftrain.policy.robot import check_env
from ftrain.train.hooks import hook_class


def check(env: EnvConfig, hooks: list[HookConfig], trackers: Sequence[str] = ()) -> None:
    """UserError if ``env`` cannot be trained, a hook does not import or takes no such kwargs, or a tracker's package
    does not import (a broken install, which would otherwise leave the run untracked after training began)."""
    check_env(env)
    for hook in hooks:
        hook_class(hook.target, hook.kwargs)
    for module in trackers:
        try:
            getattr(importlib.import_module(module), "__version__", None)  # runs wandb's code, deferred to first use
        except Exception as error:  # whatever a broken install raises
            raise UserError(
                f"log.{module} is set but {module} does not import ({error_line(error)}): repair it (pip install "
                f"--force-reinstall 'ftrain[{module}]'), or unset log.{module}"
            ) from None


if __name__ == "__main__":
    given = json.loads(sys.stdin.read())
    try:
        check(EnvConfig(**given["env"]), [HookConfig(**hook) for hook in given["hooks"]], given["trackers"])
    except UserError as error:
        print(error, file=sys.stderr)
        sys.exit(2)
