"""Which gymnasium ids ftrain trains: gymnasium's MuJoCo environments, whose exact state the trainer saves.

Checked from gymnasium's registry (each id's entry point) without building an env: this imports gymnasium but not
MuJoCo or torch, so the CLI checks the id before ``ftrain train`` starts and before ``ftrain supervise`` launches
anything (the supervisor package itself never imports gymnasium).
"""

from __future__ import annotations

import difflib

from gymnasium.envs.registration import registry

from ftrain.errors import UserError

MUJOCO_MODULES = "gymnasium.envs.mujoco."
"""Where the entry points of gymnasium's MuJoCo environments live (the -v2/-v3 ids point elsewhere: mujoco-py)."""


def mujoco_env_ids() -> list[str]:
    """The registered ids ftrain can train, sorted."""
    return sorted(
        env_id
        for env_id, spec in registry.items()
        if isinstance(spec.entry_point, str) and spec.entry_point.startswith(MUJOCO_MODULES)
    )


def check_env_id(env_id: str) -> None:
    """UserError unless ``env_id`` is a registered MuJoCo environment; the message names the supported ids."""
    supported = mujoco_env_ids()
    if env_id in supported:
        return
    if env_id not in registry:
        near = difflib.get_close_matches(env_id, supported, n=1)
        hint = f"did you mean {near[0]!r}?" if near else f"use one of {', '.join(supported)}"
        raise UserError(f"env.id={env_id!r} is not a registered gymnasium environment: {hint}")
    raise UserError(
        f"env.id={env_id!r} is not a MuJoCo environment: ftrain trains gymnasium's MuJoCo environments, "
        f"use one of {', '.join(supported)}"
    )
