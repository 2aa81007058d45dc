"""Policy rollouts in an environment of their own, and the evaluation hook that scores training with them.

Evaluation never touches what training continues from: it steps a separate environment seeded on its own, takes the
actor's deterministic (mean) actions, so no random number is drawn, and only reads the observation normalizer.
Training with and without evaluation therefore learns bit for bit the same.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gymnasium as gym
import numpy as np
import torch
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from ftrain.config import EnvConfig, EvalConfig
from ftrain.envs import OBS_GROUP
from ftrain.hooks import Hook

if TYPE_CHECKING:
    from ftrain.trainer import Trainer

Act = Callable[[torch.Tensor], torch.Tensor]
"""Actions ``[N, num_actions]`` for observations ``[N, obs_dim]``."""


@dataclass(frozen=True)
class Episode:
    ret: float
    length: int


def actor_actions(actor: MLPModel, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
    """The rsl-rl actor's actions for a batch of observations: the mean, or a sample (global torch RNG)."""
    with torch.inference_mode():
        return actor(TensorDict({OBS_GROUP: obs}, batch_size=[obs.shape[0]]), stochastic_output=not deterministic)


def make_env(env_config: EnvConfig, render: bool = False) -> gym.Env:
    """One environment as configured for training; ``render`` makes ``env.render()`` return RGB frames, seen by the
    model's ``track`` camera if it has one (gymnasium's default free camera stays put while the agent runs away)."""
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
) -> list[Episode]:
    """Play ``episodes`` episodes seeded ``seed``, ``seed + 1``, ...; ``on_observation`` sees every observation
    (after the reset and after each step, so ``sum(length + 1)`` in all)."""
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
    return results


class EvalHook(Hook):
    """Every ``eval.every`` iterations, on rank 0: ``eval.episodes`` deterministic episodes with fixed seeds.

    Their mean return becomes ``metrics["eval_return"]``, which the logging hooks after this one write and the
    checkpoint manifest stores (so keep-best retention can rank by it). On the iterations in between the metric
    is NaN: present from the first iteration on (the CSV header is written then) but never a stale score that
    keep-best could mistake for a measurement of that step.
    """

    def __init__(self, config: EvalConfig) -> None:
        self.config = config
        self.env: gym.Env | None = None

    def after_iteration(self, trainer: Trainer, metrics: dict[str, float]) -> None:
        if not trainer.info.is_main:
            return
        if trainer.iteration % self.config.every:
            metrics["eval_return"] = math.nan
            return
        if self.env is None:
            self.env = make_env(trainer.config.env)
        actor = trainer.alg.get_policy()
        episodes = rollout(self.env, lambda obs: actor_actions(actor, obs), self.config.episodes, self.config.seed)
        metrics["eval_return"] = sum(e.ret for e in episodes) / len(episodes)

    def on_end(self, trainer: Trainer) -> None:
        if self.env is not None:
            self.env.close()
