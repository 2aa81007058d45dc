"""The check of an env that ``ftrain supervise`` makes before it launches or creates anything: of the user's own, or
of gymnasium's with ``env.kwargs``.

``python -m ftrain.policy.robot ENV_JSON`` makes the env once (``robot.check_env``: the module imported, the id
registered, the model compiled, the spaces flat, a first reset and step taken with its ``kwargs``) and closes it; a
UserError is its one line and exit code 2. It runs in a child so that the supervisor stays free of MuJoCo and of the
user's module, whose import may do anything, and a bad env is refused before any worker starts or any log directory
is made.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

from ftrain.config import EnvConfig
from ftrain.errors import UserError

TIMEOUT = 120.0
"""Seconds the check may take; past them (a module that hangs on import) the workers meet the env as before, as they
do an env whose ``kwargs`` JSON cannot carry to the child (YAML dates, say)."""


def check_in_child(env: EnvConfig) -> None:
    """UserError with the child's line if ``env`` cannot be trained; anything else is left to the workers."""
    try:
        command = [sys.executable, "-m", "ftrain.policy.robot", json.dumps(dataclasses.asdict(env))]
        done = subprocess.run(command, capture_output=True, text=True, timeout=TIMEOUT)
    except (TypeError, subprocess.TimeoutExpired):  # env.kwargs that JSON cannot carry, or a module that hangs
        return
    if done.returncode == 2 and done.stderr.strip():
        raise UserError(done.stderr.strip().splitlines()[-1])
