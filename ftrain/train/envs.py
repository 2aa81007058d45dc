"""Gymnasium MuJoCo vector environments as an rsl_rl ``VecEnv``, with exact state save and restore.

Any environment whose core is a ``MujocoEnv`` (gymnasium's or the user's, see ``ftrain.policy.robot``). What must be
saved for a bitwise-exact continuation, taken from MuJoCo itself: its integration state (``mjSTATE_INTEGRATION``:
``mjSTATE_PHYSICS`` alone drifts by ~1e-15) and the quantities it derived from the last step (body positions,
velocities, forces, sensor readings: rewards read them after a step, Ant's and Humanoid's ``xpos``/``xipos`` for
instance); each sub-env's random stream and time-limit counter; this adapter's current observations and episode
buffers; and the Python state of a user's env that offers ``ftrain_state()``/``ftrain_set_state(state)``.
"""

from __future__ import annotations

import typing
from functools import cached_property

import gymnasium as gym
import mujoco
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, SyncVectorEnv
from gymnasium.wrappers import TimeLimit
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from ftrain.config import EnvConfig
from ftrain.policy import robot
from ftrain.policy.model import OBS_GROUP

_INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION
_ARRAY = "__ndarray__"
"""Marks a numpy array in the Python state of a user's env (saved as a tensor: checkpoints load weights_only)."""


class MujocoVecEnv(VecEnv):
    """``num_envs`` synchronous copies of a MuJoCo env, stepped with same-step autoreset.

    ``step`` returns ``time_outs`` (truncated and not terminated) in ``extras`` for rsl-rl's value bootstrapping,
    and the returns and lengths of the episodes that finished in ``extras["episodes"]``.
    """

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        seed: int,
        kwargs: dict | None = None,
        imports: list[str] = (),
        built: typing.Callable[[int], None] = lambda count: None,
    ) -> None:
        """``built``: called with the count after each sub-env is made (``ftrain.train.env_build.BuildWatch``)."""
        self.env_config = EnvConfig(id=env_id, imports=list(imports), num_envs=num_envs, kwargs=dict(kwargs or {}))
        made = []
        for _ in range(num_envs):
            made.append(robot.make_env(self.env_config))
            built(len(made))
        self.envs = SyncVectorEnv([lambda env=env: env for env in made], autoreset_mode=AutoresetMode.SAME_STEP)
        self.env_id = env_id
        self.num_envs = num_envs
        self.num_actions = int(np.prod(self.envs.single_action_space.shape))
        self.max_episode_length = self.envs.envs[0].spec.max_episode_steps  # set: robot.check_trainable
        self.device = "cpu"
        self.cfg = {"env_id": env_id, "num_envs": num_envs}
        self._low = self.envs.single_action_space.low
        self._high = self.envs.single_action_space.high
        space = self.envs.single_observation_space
        self._obs_buffer = np.empty((num_envs, *space.shape), dtype=space.dtype)
        # episode bookkeeping in numpy (cheap per step); episode_length_buf is rsl-rl's view of the same memory
        self._returns = np.zeros(num_envs, dtype=self.envs.single_observation_space.dtype)
        self._lengths = np.zeros(num_envs, dtype=np.int64)
        self.episode_length_buf = torch.from_numpy(self._lengths)
        self.reset(seed)
        self._bases = [env.unwrapped for env in self.envs.envs]
        self._time_limits = [_time_limit(env) for env in self.envs.envs]
        model = self._bases[0].model
        self._state_size = mujoco.mj_stateSize(model, _INTEGRATION)
        self._derived = _derived_fields(model)
        self._python_state = all(callable(getattr(self._bases[0], name, None)) for name in robot.STATE_METHODS)

    @cached_property
    def robot(self) -> dict:
        """The identity of the robot these envs simulate (``ftrain.policy.robot.identity``)."""
        return robot.identity(self.env_config, self._bases[0])

    def reset(self, seed: int) -> None:
        """Start every sub-env afresh from ``seed`` (sub-env i from ``seed + i``, gymnasium's rule)."""
        obs, _ = self.envs.reset(seed=seed)
        self.obs = torch.from_numpy(obs.astype(np.float32))
        self._returns[:] = 0
        self._lengths[:] = 0

    def reseed(self, seed: int) -> None:
        """New random streams for every sub-env (sub-env i from ``seed + i``, as ``reset``), without a reset: what
        they draw from here on (where their next episodes start)."""
        for index, base in enumerate(self._bases):
            base.np_random, _ = gym.utils.seeding.np_random(seed + index)

    @property
    def num_obs(self) -> int:
        return self.obs.shape[1]

    def get_observations(self) -> TensorDict:
        return TensorDict({OBS_GROUP: self.obs}, batch_size=[self.num_envs])

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """What gymnasium's ``SyncVectorEnv.step`` does with same-step autoreset (a finished sub-env is reset at
        once and returns its first observation), without merging the sub-envs' info dicts, which ftrain does not
        read and which cost a fifth of a cheap env's step."""
        clipped = np.clip(actions.numpy(), self._low, self._high)
        obs, rewards = self._obs_buffer, np.empty(self.num_envs)
        terminated, truncated = np.empty(self.num_envs, dtype=bool), np.empty(self.num_envs, dtype=bool)
        for index, (env, action) in enumerate(zip(self.envs.envs, clipped, strict=True)):
            obs[index], rewards[index], terminated[index], truncated[index], _ = env.step(action)
            if terminated[index] or truncated[index]:
                obs[index], _ = env.reset()
        self.obs = torch.from_numpy(obs.astype(np.float32))
        done = terminated | truncated
        self._returns += rewards
        self._lengths += 1
        finished = np.flatnonzero(done)
        episodes = (self._returns[finished].tolist(), self._lengths[finished].tolist())
        self._returns[finished] = 0
        self._lengths[finished] = 0
        extras = {"time_outs": torch.from_numpy(truncated & ~terminated), "episodes": episodes}
        return self.get_observations(), torch.from_numpy(rewards.astype(np.float32)), torch.from_numpy(done), extras

    def running_episodes(self) -> tuple[float, float]:
        """The mean return and length of this rank's episodes under way (what the console shows until one ends)."""
        return float(self._returns.mean()), float(self._lengths.mean())

    def get_state(self) -> dict:
        """Everything needed to continue bit for bit, as tensors, numbers and lists (weights_only-loadable).

        One row per sub-env in a few stacked tensors: a checkpoint's encoding time grows with its tensor count.
        """
        bases = self._bases
        physics = np.empty((self.num_envs, self._state_size))
        for row, base in zip(physics, bases, strict=True):
            mujoco.mj_getState(base.model, base.data, row, _INTEGRATION)
        state = {
            "env_id": self.env_id,
            "physics": torch.from_numpy(physics),
            "derived": torch.from_numpy(
                np.stack([np.concatenate([getattr(b.data, name).ravel() for name in self._derived]) for b in bases])
            ),
            "derived_fields": list(self._derived),
            "rng": _rng_state(self._bit_generators()),
            "elapsed_steps": [limit._elapsed_steps if limit else None for limit in self._time_limits],
            "obs": self.obs.clone(),
            "episode_length": torch.from_numpy(self._lengths.copy()),
            "episode_return": torch.from_numpy(self._returns.copy()),
        }
        if self._python_state:
            state["python"] = [_plain(base.ftrain_state()) for base in bases]
        return state

    def set_state(self, state: dict) -> None:
        saved_envs, saved_size = state["physics"].shape
        if state["env_id"] != self.env_id or saved_envs != self.num_envs:
            raise ValueError(
                f"environment state is for {saved_envs} x {state['env_id']}, "
                f"this env is {self.num_envs} x {self.env_id}"
            )
        if saved_size != self._state_size or state.get("derived_fields", self._derived) != self._derived:
            raise ValueError(f"environment state is for another model of {self.env_id} (its robot has changed)")
        for index, (base, limit) in enumerate(zip(self._bases, self._time_limits, strict=True)):
            mujoco.mj_setState(base.model, base.data, state["physics"][index].numpy(), _INTEGRATION)
            _set_derived(base.data, state, index, self._derived)
            if limit is not None:
                limit._elapsed_steps = state["elapsed_steps"][index]
            if self._python_state and "python" in state:
                base.ftrain_set_state(_unplain(state["python"][index]))
        _set_rng_state(self._bit_generators(), state["rng"])
        self.obs = state["obs"].clone()
        self._lengths[:] = state["episode_length"].numpy()
        self._returns[:] = state["episode_return"].numpy()

    def close(self) -> None:
        self.envs.close()

    def _bit_generators(self) -> list[np.random.BitGenerator]:
        """Looked up each time: a reset with a seed gives a sub-env a new generator."""
        return [base.np_random.bit_generator for base in self._bases]


ROW_FIELDS = ("physics", "derived", "obs", "episode_length", "episode_return", "rng", "elapsed_steps", "python")
ROW_FIELDS += ("xpos", "xipos")  # (state format 4's)
"""The fields of ``get_state`` with a row per sub-env (tensors, or lists: the rest describe the model)."""


def take_rows(states: list[dict], first: int, count: int) -> dict:
    """The state of ``count`` sub-envs from ``first`` on, of the sub-envs of ``states`` (``get_state``'s, in order)
    taken as one row after the other: how an environment's state goes to whichever rank holds its global index."""
    taken = dict(states[0])
    for name in ROW_FIELDS:
        rows = [state[name] for state in states if name in state]
        if not rows:
            continue
        if isinstance(rows[0], torch.Tensor):
            taken[name] = torch.cat(rows)[first : first + count].clone()
        else:
            taken[name] = [row for part in rows for row in part][first : first + count]
    return taken


def _derived_fields(model: mujoco.MjModel) -> list[str]:
    """The arrays of MuJoCo's data that it derives from the state and that keep their size (the model's): those of
    a fresh ``MjData`` with any element (contacts and constraints come and go: the next step computes them anew)."""
    fresh = mujoco.MjData(model)
    names = []
    for name in dir(fresh):
        value = getattr(fresh, name, None) if not name.startswith("_") else None
        if isinstance(value, np.ndarray) and value.dtype == np.float64 and value.size:
            names.append(name)
    return names


def _set_derived(data: mujoco.MjData, state: dict, index: int, names: list[str]) -> None:
    if "derived" not in state:  # state format 4 of before user envs: only the body positions rewards read
        data.xpos[:] = state["xpos"][index].numpy()
        data.xipos[:] = state["xipos"][index].numpy()
        return
    row, start = state["derived"][index].numpy(), 0
    for name in names:
        target = getattr(data, name)
        target.ravel()[:] = row[start : start + target.size]
        start += target.size


def _plain(value: object) -> object:
    """The Python state of a user's env as checkpoint data: numpy arrays as tensors, numpy scalars as numbers."""
    if isinstance(value, np.ndarray):
        return {_ARRAY: torch.from_numpy(value.copy())}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    return value


def _unplain(value: object) -> object:
    """What ``_plain`` made, back (tuples come back as lists)."""
    if isinstance(value, dict):
        if list(value) == [_ARRAY]:
            return value[_ARRAY].numpy().copy()
        return {key: _unplain(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_unplain(item) for item in value]
    return value


def _rng_state(generators: list[np.random.BitGenerator]) -> torch.Tensor | list[dict]:
    """The sub-envs' random states. PCG64 (gymnasium's) as one int64 tensor, a row per sub-env: the 128-bit state
    and increment as two 64-bit words each (high, low; two's complement), then ``has_uint32`` and ``uinteger``; a
    tensor costs a save far less than 16 nested dicts of big ints. Any other bit generator: numpy's state dicts."""
    states = [generator.state for generator in generators]
    if any(state["bit_generator"] != "PCG64" for state in states):
        return states
    numbers = b"".join(state["state"][key].to_bytes(16, "little") for state in states for key in ("state", "inc"))
    words = np.frombuffer(numbers, dtype="<i8").reshape(-1, 2, 2)[:, :, ::-1].reshape(-1, 4)  # (low, high) reversed
    flags = np.array([(state["has_uint32"], state["uinteger"]) for state in states], dtype=np.int64)
    return torch.from_numpy(np.concatenate([words, flags], axis=1))


def _set_rng_state(generators: list[np.random.BitGenerator], saved: torch.Tensor | list[dict]) -> None:
    if not isinstance(saved, torch.Tensor):  # state dicts (also what checkpoints of state format 2 hold)
        for generator, state in zip(generators, saved, strict=True):
            generator.state = state
        return
    for generator, row in zip(generators, saved.tolist(), strict=True):
        state_high, state_low, inc_high, inc_low, has_uint32, uinteger = row
        generator.state = {
            "bit_generator": "PCG64",
            "state": {"state": _join(state_high, state_low), "inc": _join(inc_high, inc_low)},
            "has_uint32": has_uint32,
            "uinteger": uinteger,
        }


_MASK64 = (1 << 64) - 1


def _join(high: int, low: int) -> int:
    return ((high & _MASK64) << 64) | (low & _MASK64)


def _time_limit(env: gym.Env) -> TimeLimit | None:
    """The time limit among ``env``'s wrappers (None: it has none)."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, TimeLimit):
            return env
        env = env.env
    return None
