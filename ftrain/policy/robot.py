"""The robot a policy controls: a gymnasium environment whose core (``env.unwrapped``) is a
``gymnasium.envs.mujoco.MujocoEnv``, gymnasium's own or the user's, made and checked here for every process that
makes one (each training rank, evaluation, ``play``, ``export``).

A user's environment lives in their own module, found in the working directory or among the installed packages:
named in the id as gymnasium names it (``env.id=mybot:MyRobot-v0``: importing ``mybot`` registers ``MyRobot-v0``),
or listed in ``env.imports`` (then ``env.id=MyRobot-v0``). Whatever makes an environment untrainable is a UserError
of one line: a module that does not import (the import error's own line), an id nobody registered (with the ids the
modules did register), a model that does not compile (MuJoCo's message, with the file), a core that is not a
MujocoEnv, an observation or action space that is not a flat Box.

``identity`` describes a robot for the config hash and the manifests: its env class and the SHA-256 of every file of
its MJCF model, so that a resume notices an edited robot, and whether its Python state (what MuJoCo does not hold)
is saved.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import sys
import traceback
from pathlib import Path

import gymnasium as gym
import numpy as np
from gymnasium.envs.mujoco import MujocoEnv
from gymnasium.envs.registration import registry

from ftrain.config import EnvConfig
from ftrain.errors import UserError, closest, error_line, module_missing, short_path
from ftrain.policy import mjcf
from ftrain.policy.mujoco_warnings import route_mujoco_warnings

GYMNASIUM_MUJOCO = "gymnasium.envs.mujoco"
STATE_METHODS = ("ftrain_state", "ftrain_set_state")
"""The optional pair of methods on a user's env core that save and restore the Python state MuJoCo does not hold:
``ftrain_state()`` returns plain data (numbers, strings, lists, dicts, numpy arrays, tensors), and
``ftrain_set_state(state)`` receives it back on a resume. (``set_state`` is taken: MujocoEnv's sets qpos and qvel.)"""
PROBE_STEPS = 8
"""Steps a throwaway env takes to see which of its attributes change as it runs."""


def make_env(env: EnvConfig, render: bool = False) -> gym.Env:
    """One environment as configured (its modules imported first), checked; UserError if it cannot be trained.

    ``render``: ``env.render()`` returns RGB frames (the env's own ``render_mode="rgb_array"``); gymnasium's own
    models are seen through their ``track`` camera (its default free camera stays put while the agent runs away).
    """
    route_mujoco_warnings()
    added = import_env_modules(env)
    check_registered(env, added)
    kwargs = dict(env.kwargs)
    if render:
        kwargs["render_mode"] = "rgb_array"
        if _entry_module(env.id).startswith(GYMNASIUM_MUJOCO) and "camera_id" not in kwargs:
            kwargs.setdefault("camera_name", "track")
    try:
        made = gym.make(env.id, **kwargs)
    except Exception as error:  # the user's constructor and model: bad input, said in one line
        raise UserError(_construction_error(env.id, error)) from None
    try:
        check_trainable(env, made)
    except UserError:
        made.close()
        raise
    return made


def check_env(env: EnvConfig) -> None:
    """UserError if ``env`` cannot be trained: ``make_env``'s checks, then a first reset and step, where a value of
    ``env.kwargs`` that the constructor takes but the physics or the reward cannot use (a string for a number) would
    otherwise crash every worker, and every restart."""
    made = make_env(env)
    try:
        space = made.action_space
        made.reset(seed=0)
        made.step(np.clip(np.zeros(space.shape, dtype=space.dtype), space.low, space.high))
    except Exception as error:  # the user's env and values: bad input, said in one line
        raise UserError(
            f"env.id={env.id!r} fails on its first reset or step: {error_line(error)}: fix env.kwargs or the env"
        ) from None
    finally:
        made.close()


def import_env_modules(env: EnvConfig) -> set[str]:
    """Import the modules ``env`` names (``env.imports``, the module of a ``module:EnvId`` id), from the working
    directory or the installed packages, as ``python -m`` would; the ids their imports registered."""
    if os.getcwd() not in sys.path:
        sys.path.insert(0, os.getcwd())  # the ``ftrain`` script, unlike ``python -m``, does not look there
    before = set(registry)
    for name in env_modules(env):
        key = "env.imports" if name in env.imports else "env.id"
        try:
            importlib.import_module(name)
        except Exception as error:  # whatever the user's module raises
            fix = (
                "run ftrain from the directory that holds it, or install it (pip install -e your package)"
                if module_missing(error, name)
                else "fix the module"
            )
            raise UserError(f"{key}: module {name!r} does not import ({error_line(error)}): {fix}") from None
    return set(registry) - before


def env_modules(env: EnvConfig) -> list[str]:
    """The modules to import before ``env`` can be made."""
    module, sep, _ = env.id.rpartition(":")
    return [*env.imports, *([module] if sep else [])]


def check_registered(env: EnvConfig, added: set[str]) -> None:
    """UserError unless ``env.id`` is registered (by gymnasium, or by the imported modules)."""
    name = env.id.rpartition(":")[2]
    if name in registry:
        return
    modules = env_modules(env)
    if modules:
        theirs = sorted(added | {env_id for env_id in registry if _entry_module(env_id).startswith(tuple(modules))})
        did = f"they registered {', '.join(theirs)}" if theirs else "they registered none"
        raise UserError(
            f"env.id={env.id!r}: importing {', '.join(modules)} registered no environment {name!r} ({did}): use one "
            f"of those, or register it in the module (gymnasium.register(id={name!r}, entry_point=...))"
        )
    near = closest(name, registry)
    hint = (
        f"did you mean {near!r}?"
        if near
        else f"for an environment of your own, name its module: env.id=mymodule:{name}"
    )
    raise UserError(f"env.id={env.id!r} is not a registered gymnasium environment: {hint}")


def check_trainable(config: EnvConfig, env: gym.Env) -> None:
    """UserError unless ``env``'s core is a MujocoEnv with flat Box observation and action spaces, and its episodes
    end at a time limit: an episode that never ends (HalfCheetah falls on no step) is never evaluated nor played."""
    env_id, core = config.id, env.unwrapped
    if not isinstance(core, MujocoEnv):
        raise UserError(
            f"env.id={env_id!r} is a {class_name(type(core))}, not a gymnasium.envs.mujoco.MujocoEnv: ftrain trains "
            "MuJoCo environments (it saves their exact state from MuJoCo): derive the env's class from MujocoEnv"
        )
    for what, space in (("observation", env.observation_space), ("action", env.action_space)):
        if not (isinstance(space, gym.spaces.Box) and len(space.shape) == 1):
            raise UserError(
                f"env.id={env_id!r} has the {what} space {space}: ftrain trains a flat Box (one vector of numbers) "
                f"of each: flatten it (gymnasium.spaces.flatten_space) or make it continuous"
            )
    if env.spec is None or env.spec.max_episode_steps is None:
        given = config.kwargs.get("max_episode_steps")
        why = (
            f"env.kwargs max_episode_steps={given} leaves env.id={env_id!r} without a time limit"
            if given is not None
            else f"env.id={env_id!r} has no time limit (gymnasium's max_episode_steps, of its registration)"
        )
        raise UserError(
            f"{why}: an episode may never end, and then is never evaluated nor played: set one, e.g. "
            "env.kwargs={max_episode_steps: 1000}"
        )


def identity(env: EnvConfig, core: MujocoEnv) -> dict:
    """The robot of ``core``: its env class, the SHA-256 of every file of its model (named relative to the main XML
    file), a digest of both, whether both are gymnasium's own, and what happens to its Python state on a resume."""
    model = mjcf.file_digests(core.fullpath)
    cls = class_name(type(core))
    gymnasium_dir = Path(gym.__file__).parent
    builtin = type(core).__module__.startswith(GYMNASIUM_MUJOCO) and Path(core.fullpath).is_relative_to(gymnasium_dir)
    digest = hashlib.sha256(json.dumps({"env_class": cls, "mjcf": model}, sort_keys=True).encode()).hexdigest()
    return {
        "env_class": cls,
        "mjcf": model,
        "digest": digest[:16],
        "builtin": builtin,
        "python_state": _python_state(env, core),
    }


def unsaved_state_notice(robot: dict) -> str | None:
    """The one line to tell when a resume of this robot is exact only for its physics (None: it is exact)."""
    state = robot["python_state"]
    if not state.startswith("NOT saved"):
        return None
    return (
        f"env {robot['env_class']} keeps Python state that ftrain cannot save ({state.partition(': ')[2]} changed as "
        "it ran): a resume restores its physics, time limit and random stream exactly, not that state; define "
        f"{STATE_METHODS[0]}() and {STATE_METHODS[1]}(state) on the env to make a resume exact"
    )


def class_name(cls: type) -> str:
    return f"{cls.__module__}:{cls.__qualname__}"


def _construction_error(env_id: str, error: Exception) -> str:
    """Why ``gym.make(env_id)`` failed, in one line."""
    model = _model_path(error)
    if isinstance(error, ValueError) and model is not None:  # MuJoCo's compiler refused the model
        message = " ".join(str(error).split())
        return f"env.id={env_id!r}: its MuJoCo model {short_path(model)} does not compile ({message}): fix the XML"
    if isinstance(error, TypeError) and "unexpected keyword argument" in str(error):
        return f"env.kwargs for {env_id!r} are not accepted: {' '.join(str(error).split())}"
    if isinstance(error, OSError) and "does not exist" in str(error):  # MujocoEnv: the model file is not there
        return f"env.id={env_id!r}: {error}: fix the model path (the env's xml_file or model_path)"
    return f"env.id={env_id!r} cannot be made: {error_line(error)}: fix the env or env.kwargs"


def _model_path(error: BaseException) -> str | None:
    """The model file a MujocoEnv was compiling when ``error`` was raised, if it was."""
    for frame, _ in traceback.walk_tb(error.__traceback__):
        if frame.f_code.co_name == "_initialize_simulation" and isinstance(frame.f_locals.get("self"), MujocoEnv):
            return frame.f_locals["self"].fullpath
    return None


def _entry_module(env_id: str) -> str:
    """The module of the registered entry point of ``env_id`` ('' if not registered or not known)."""
    spec = registry.get(env_id.rpartition(":")[2])
    entry = spec.entry_point if spec is not None else None
    return entry.partition(":")[0] if isinstance(entry, str) else getattr(entry, "__module__", "")


def _python_state(env: EnvConfig, core: MujocoEnv) -> str:
    """``saved by ftrain_state()``, ``none seen``, or ``NOT saved: <attributes>``: the attributes of the env core
    that changed while a throwaway copy stepped and reset (MuJoCo's model and data, renderers and other objects are
    not compared: only numbers, strings, arrays and containers of them)."""
    if all(callable(getattr(core, method, None)) for method in STATE_METHODS):
        return f"saved by {STATE_METHODS[0]}()"
    probe = make_env(env)
    try:
        space = probe.action_space
        low, high = np.nan_to_num(space.low, neginf=-1.0), np.nan_to_num(space.high, posinf=1.0)
        rng = np.random.default_rng(0)
        probe.reset(seed=0)
        seen = [_attributes(probe.unwrapped)]
        for _ in range(PROBE_STEPS):
            _, _, terminated, truncated, _ = probe.step(rng.uniform(low, high).astype(space.dtype))
            seen.append(_attributes(probe.unwrapped))
            if terminated or truncated:
                probe.reset()
        probe.reset(seed=1)
        seen.append(_attributes(probe.unwrapped))
    finally:
        probe.close()
    names = {name for attributes in seen for name in attributes}
    changed = sorted(name for name in names if any(a.get(name) != seen[0].get(name) for a in seen[1:]))
    return f"NOT saved: {', '.join(changed)}" if changed else "none seen"


def _attributes(core: MujocoEnv) -> dict:
    return {name: _fingerprint(value) for name, value in vars(core).items() if not name.startswith("_np_random")}


def _fingerprint(value: object, depth: int = 0) -> object:
    """A comparable copy of plain data; None for anything else."""
    if isinstance(value, float):
        return value.hex()  # NaN equals itself
    if value is None or isinstance(value, (bool, int, str, bytes)):
        return value
    if isinstance(value, np.generic):
        return _fingerprint(value.item())
    if isinstance(value, np.ndarray):
        return (value.dtype.str, value.shape, value.tobytes())
    if isinstance(value, np.random.Generator):  # a random stream of the env's own
        return _fingerprint(value.bit_generator.state, depth)
    if depth < 3 and isinstance(value, (list, tuple)):
        return tuple(_fingerprint(item, depth + 1) for item in value)
    if depth < 3 and isinstance(value, dict):
        return tuple((str(key), _fingerprint(item, depth + 1)) for key, item in value.items())
    return None
