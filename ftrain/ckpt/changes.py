"""What a resume changes: the training keys of the config (old -> new) and the robot's files, in words.

A resume refused for a changed config names what changed, and one that goes on anyway (``allow_config_change=true``,
or a lengthened run whose learning rate follows its length: ``ftrain.ckpt.resume``) says so in one line, which the run
also records (``metrics.csv``'s ``config_change``, the supervisor's ``resumed`` event) and ``ftrain plot`` marks as a
change, not a plain resume.
"""

from __future__ import annotations

import functools
import json

from ftrain.config import KEYS_ADDED_LATER, Config, training_part
from ftrain.values import dotted


def config_change(saved: dict, current: dict, saved_robot: dict | None, robot: dict | None) -> str | None:
    """What differs, as ``key old -> new`` for each training key and the robot's change; None: nothing.

    ``saved``: a manifest's ``config`` (``public_dict``), ``current``: this run's ``public_dict``; ``saved_robot``,
    ``robot``: their robots' identities (``ftrain.policy.robot.identity``; None: not known)."""
    before, now = _training_keys(saved), _training_keys(current)
    parts = [f"{key} {_text(before.get(key))} -> {_text(now.get(key))}" for key in _differing(before, now)]
    if changed := robot_change(saved_robot, robot):
        parts.append(f"robot: {changed}")
    return "; ".join(parts) or None


MODEL_FREE = ("obs_normalization_until", "obs_clip", "init_noise_std", "final_noise_std")
"""Policy keys that do not decide the models' tensors (when the normalizers freeze, where their output is clipped,
where the action noise starts and ends): a change of them is a config change, which ``allow_config_change`` lets
through."""


def model_change(saved: dict, current: dict) -> str | None:
    """What differs in the environment and the policy keys that decide the models' tensors, as ``key old -> new``
    (``saved``, ``current``: as for ``config_change``); None: the models load into each other."""
    before, now = _model_keys(saved), _model_keys(current)
    keys = sorted(key for key in before.keys() | now.keys() if before.get(key) != now.get(key))
    return "; ".join(f"{key} {_text(before.get(key))} -> {_text(now.get(key))}" for key in keys) or None


def _model_keys(config: dict) -> dict:
    policy = {f"policy.{key}": value for key, value in dotted(config["policy"]).items() if key not in MODEL_FREE}
    return {"env.id": config["env"]["id"], **policy}


def changed_keys(saved: dict, current: dict) -> list[str]:
    """The training keys (dotted) whose values differ between two configs as dicts (``config_change``)."""
    return _differing(_training_keys(saved), _training_keys(current))


def _differing(before: dict, now: dict) -> list[str]:
    return [key for key in sorted(before.keys() | now.keys()) if before.get(key) != now.get(key)]


def _training_keys(config: dict) -> dict:
    """``training_part`` dotted, with the keys it leaves out at their defaults (``KEYS_ADDED_LATER``) back at them: a
    section set now beside one left at its defaults then differs in the key set, not in every key ("reward.clip
    (unset) -> 10.0" named a key nobody changed)."""
    return {**_added_later_defaults(), **dotted(training_part(config))}


@functools.cache
def _added_later_defaults() -> dict:
    within = tuple(f"{key}." for key in KEYS_ADDED_LATER)  # the leaves of a section added later
    return {
        key: value
        for key, value in dotted(Config().to_dict()).items()
        if key in KEYS_ADDED_LATER or key.startswith(within)
    }


def robot_change(saved: dict | None, current: dict | None) -> str | None:
    """What differs between the robot a checkpoint recorded and the one trained now, in words (None: nothing, or
    one of them is not known)."""
    if saved is None or current is None:
        return None
    if saved["env_class"] != current["env_class"]:
        return f"its env class was {saved['env_class']}, now {current['env_class']}"
    before, now = saved["mjcf"], current["mjcf"]
    for name in [*before, *(name for name in now if name not in before)]:
        if name not in now:
            return f"its model no longer uses {name}"
        if name not in before:
            return f"its model now uses {name}, which it did not"
        if before[name] != now[name]:
            return f"{name} has changed (sha256 {before[name][:12]}, now {now[name][:12]})"
    return None


def _text(value: object) -> str:
    return "(unset)" if value is None else json.dumps(value) if isinstance(value, (dict, list, str)) else str(value)
