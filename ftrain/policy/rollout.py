"""Policy rollouts in a gymnasium environment of their own (evaluation, play, export checks).

A rollout never touches a training state: a separate environment, seeded on its own; deterministic actions draw
no random number.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

Act = Callable[[torch.Tensor], torch.Tensor]
"""Actions ``[N, num_actions]`` for observations ``[N, obs_dim]``."""


@dataclass(frozen=True)
class Episode:
    ret: float
    length: int


def rollout(
    envs: gym.Env | Sequence[gym.Env],
    act: Act,
    episodes: int,
    seed: int,
    on_observation: Callable[[np.ndarray], None] | None = None,
    on_episode: Callable[[int, Episode], None] | None = None,
    rows: tuple[int, int] | None = None,
) -> list[Episode]:
    """Play ``episodes`` episodes seeded ``seed``, ``seed + 1``, ..., returned in that order.

    With several envs, as many episodes run at once, in lock step with one batched ``act`` call per step (evaluation
    is then mostly environment stepping); an env whose episode ends starts the next one. ``on_observation`` (for one
    env) sees every observation: after the reset and after each step, so ``sum(length + 1)`` in all; ``on_episode``
    each finished episode with its number (from 1), as it ends.

    ``rows``, ``(first, size)``: each step's observations go into a fresh batch of ``size`` rows of zeros, episode
    ``i``'s at row ``first + i``. A matrix product's row depends only on its own input for one shape of batch, not on
    the rows beside it, but it rounds otherwise in another shape: so an episode acts alike whether it runs alone or
    beside others, on one rank or on several (evaluation shares its episodes among the ranks; ``play`` runs them one
    after another), and they return the same, bit for bit.
    """
    envs = [envs] if isinstance(envs, gym.Env) else list(envs)
    low, high = envs[0].action_space.low, envs[0].action_space.high
    results: list[Episode] = [Episode(0.0, 0)] * episodes
    pending = iter(range(episodes))
    running: list[_Running] = []

    def begin(env: gym.Env) -> None:
        index = next(pending, None)
        if index is not None:
            obs, _ = env.reset(seed=seed + index)
            if on_observation is not None:
                on_observation(obs)
            running.append(_Running(env, index, obs))

    for env in envs:
        begin(env)
    while running:
        observations = torch.as_tensor(np.stack([run.obs for run in running]), dtype=torch.float32)
        if rows is None:
            actions = act(observations)
        else:
            placed = [rows[0] + run.index for run in running]
            batch = torch.zeros(rows[1], observations.shape[1])  # fresh: aligned as every tensor, which rounding sees
            batch[placed] = observations
            actions = act(batch)[placed]
        for run, action in zip(list(running), actions.numpy().astype(np.float64), strict=True):
            run.obs, reward, terminated, truncated, _ = run.env.step(np.clip(action, low, high))
            if on_observation is not None:
                on_observation(run.obs)
            run.ret += float(reward)
            run.length += 1
            if terminated or truncated:
                results[run.index] = Episode(run.ret, run.length)
                if on_episode is not None:
                    on_episode(run.index + 1, results[run.index])
                running.remove(run)
                begin(run.env)
    return results


@dataclass
class _Running:
    """An episode under way in ``env``."""

    env: gym.Env
    index: int
    obs: np.ndarray
    ret: float = 0.0
    length: int = 0
