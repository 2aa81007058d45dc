"""The supervisor's check of the user's code before it launches or creates anything: ``python -m
ftrain.train.user_code`` in a child (the env made once, the hooks' modules imported and their kwargs checked), so
that the supervisor stays free of torch, MuJoCo and the user's modules, whose import may do anything. Asked only where
there is user code (``has_user_code``): gymnasium's own envs with their default arguments are checked by id. A
refusal is the child's one line as a UserError; anything else (a crash, a hang past ``TIMEOUT``) is left to the
workers, which check again.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

from ftrain.config import EnvConfig, HookConfig
from ftrain.errors import UserError

TIMEOUT = 120.0
"""Seconds the child may take; past them (a module that hangs on import) the workers meet the code as before, as they
do values that JSON cannot carry to the child (YAML dates in ``env.kwargs``, say)."""


def has_user_code(env: EnvConfig, hooks: list[HookConfig], trackers: list[str]) -> bool:
    """Whether the run runs code beyond gymnasium's own envs with their default arguments (a tracker's package is
    the user's install)."""
    return ":" in env.id or bool(env.imports or env.kwargs or hooks or trackers)


def check_in_child(env: EnvConfig, hooks: list[HookConfig], trackers: list[str]) -> None:
    """UserError with the child's line if ``env`` cannot be trained, a hook does not import or takes no such kwargs,
    or a tracker's package does not import."""
    try:
        hooks_given = [{"target": hook.target, "kwargs": dict.fromkeys(hook.kwargs)} for hook in hooks]  # names
        config = {"env": dataclasses.asdict(env), "hooks": hooks_given, "trackers": trackers}
        command = [sys.executable, "-m", "ftrain.train.user_code"]  # the config on stdin: out of ``ps``, for secrets
        done = subprocess.run(command, input=json.dumps(config), capture_output=True, text=True, timeout=TIMEOUT)
    except (TypeError, subprocess.TimeoutExpired):  # values that JSON cannot carry, or a module that hangs
        return
    if done.returncode == 2 and done.stderr.strip():
        raise UserError(done.stderr.strip().splitlines()[-1])
