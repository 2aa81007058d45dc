"""The env id check ``ftrain supervise`` makes before it launches anything: gymnasium's registry only.

It imports gymnasium but not MuJoCo, torch or the user's module (the supervisor stays free of them), so it checks
only ids of gymnasium's own. An env of the user's (``module:EnvId``, or an id registered by ``env.imports``) the
supervisor has made once in a child (``ftrain.supervise.user_check``), and each worker makes it again
(``ftrain.policy.robot``), refusing it in one line with exit code 2, which is what plain torchrun relies on.
"""

from __future__ import annotations

from gymnasium.envs.registration import registry

from ftrain.config import EnvConfig
from ftrain.errors import UserError, closest

MUJOCO_MODULES = "gymnasium.envs.mujoco."
"""Where the entry points of gymnasium's MuJoCo environments live (the -v2/-v3 ids point elsewhere: mujoco-py)."""


def mujoco_env_ids() -> list[str]:
    """gymnasium's own ids that ftrain can train, sorted."""
    return sorted(
        env_id
        for env_id, spec in registry.items()
        if isinstance(spec.entry_point, str) and spec.entry_point.startswith(MUJOCO_MODULES)
    )


def check_env_id(env: EnvConfig) -> None:
    """UserError unless ``env.id`` is one of gymnasium's MuJoCo environments or the user's (checked later)."""
    if ":" in env.id or env.imports:
        return  # the user's: the workers import the module and check the env
    supported = mujoco_env_ids()
    if env.id in supported:
        return
    if env.id not in registry:
        near = closest(env.id, supported)
        hint = f"did you mean {near!r}?" if near else f"use one of {', '.join(supported)}"
        raise UserError(
            f"env.id={env.id!r} is not a registered gymnasium environment: {hint} (an env of your own: "
            f"env.id=yourmodule:{env.id or 'EnvId'})"
        )
    raise UserError(
        f"env.id={env.id!r} is not a MuJoCo environment: ftrain trains environments whose core is a MujocoEnv, "
        f"gymnasium's ({', '.join(supported)}) or your own (env.id=yourmodule:EnvId)"
    )
