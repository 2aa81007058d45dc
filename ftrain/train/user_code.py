"""The user's code a run needs, checked before anything is taken (a lease, a log directory, a rendezvous): the env
(``ftrain.policy.robot.check_env``: its module imported, its id registered, its model compiled, its spaces flat, a
first reset and step with its ``kwargs``), then the modules of its hooks (``hooks.hook_target``), which the env's
``imports`` may be what they need. Whatever fails is a UserError of one line.

``ftrain train`` calls ``check`` in its own process; ``ftrain supervise`` runs ``python -m ftrain.train.user_code
CONFIG_JSON`` in a child (``ftrain.supervise.user_check``), which prints the line on stderr and exits 2.
"""

from __future__ import annotations

import json
import sys

from ftrain.config import EnvConfig, HookConfig
from ftrain.errors import UserError
from ftrain.policy.robot import check_env
from ftrain.train.hooks import hook_target


def check(env: EnvConfig, hooks: list[HookConfig]) -> None:
    """UserError if ``env`` cannot be trained or a hook's module does not import."""
    check_env(env)
    for hook in hooks:
        hook_target(hook.target)


if __name__ == "__main__":
    given = json.loads(sys.argv[1])
    try:
        check(EnvConfig(**given["env"]), [HookConfig(**hook) for hook in given["hooks"]])
    except UserError as error:
        print(error, file=sys.stderr)
        sys.exit(2)
