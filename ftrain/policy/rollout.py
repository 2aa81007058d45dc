"""Policy rollouts in a gymnasium environment of their own (evaluation, play, export checks).

A rollout never touches a training state: a separate environment, seeded on its own; deterministic actions draw
no random number.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from ftrain.config import EnvConfig
from ftrain.policy.mujoco_warnings import route_mujoco_warnings

Act = Callable[[torch.Tensor], torch.Tensor]
"""Actions ``[N, num_actions]`` for observations ``[N, obs_dim]``."""


@dataclass(frozen=True)
class Episode:
    ret: float
    length: int


def make_env(env_config: EnvConfig, render: bool = False) -> gym.Env:
    """One environment as configured for training; ``render`` makes ``env.render()`` return RGB frames, seen by the
    model's ``track`` camera if it has one (gymnasium's default free camera stays put while the agent runs away)."""
    route_mujoco_warnings()
    kwargs = dict(env_config.kwargs)
    if render:
        kwargs["render_mode"] = "rgb_array"
        if "camera_id" not in kwargs:
            kwargs.setdefault("camera_name", "track")
    return gym.make(env_config.id, **kwargs)


def rollout(
    env: gym.Env,
    act: Act,
    episodes: int,
    seed: int,
    on_observation: Callable[[np.ndarray], None] | None = None,
    on_episode: Callable[[int, Episode], None] | None = None,
) -> list[Episode]:
    """Play ``episodes`` episodes seeded ``seed``, ``seed + 1``, ...; ``on_observation`` sees every observation
    (after the reset and after each step, so ``sum(length + 1)`` in all), ``on_episode`` each finished episode with its
    number (from 1)."""
    low, high = env.action_space.low, env.action_space.high
    results = []
    for index in range(episodes):
        obs, _ = env.reset(seed=seed + index)
        total, length, done = 0.0, 0, False
        while not done:
            if on_observation is not None:
                on_observation(obs)
            action = act(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))[0]
            obs, reward, terminated, truncated, _ = env.step(np.clip(action.numpy().astype(np.float64), low, high))
            total += float(reward)
            length += 1
            done = terminated or truncated
        if on_observation is not None:
            on_observation(obs)
        results.append(Episode(total, length))
        if on_episode is not None:
            on_episode(index + 1, results[-1])
    return results
