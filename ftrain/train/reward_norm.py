"""Reward normalisation: rewards divided by the running standard deviation of the discounted return, then clipped.

Why: rsl-rl's PPO learns its value function on the raw reward scale, which differs by orders of magnitude between
environments and grows as the policy improves; value targets of hundreds swamp the policy's gradient in the shared
loss and make the value clipping meaningless. Scaling by the std of the discounted return (SB3's VecNormalize;
Engstrom et al. 2020, "Implementation Matters in Deep RL") keeps the value targets near unit scale. The mean is not
subtracted: the sign of a reward (alive bonus, falling) is information.

Across ranks: each rank keeps the discounted return of each of its environments (rank state). The statistics
(count, mean and variance of those returns) are shared: frozen during an iteration, so every rank scales with the
same numbers, and updated once at its end from all ranks' returns in one float64 all-reduce (common state). No
per-step collective; the first iteration, before any statistics, leaves rewards unscaled.
"""

from __future__ import annotations

import math

import torch

from ftrain.comm.collectives import Comm
from ftrain.config import Config

EPSILON = 1e-8
"""Added to the variance before the square root (SB3's default)."""


class RewardNormalizer:
    def __init__(
        self,
        num_envs: int,
        num_steps: int,
        gamma: float,
        clip: float,
        comm: Comm,
    ) -> None:
        self.gamma = gamma
        self.clip = clip
        self.comm = comm
        """How the ranks meet: the statistics' sum goes through it."""
        self.returns = torch.zeros(num_envs, dtype=torch.float64)
        """Each environment's discounted return since its episode began."""
        self.count = 0.0
        self.mean = 0.0
        self.var = 1.0
        self._seen = torch.empty(num_steps, num_envs, dtype=torch.float64)
        """This iteration's discounted returns, a row per step: what the statistics are updated from."""
        self._steps = 0

    @property
    def scale(self) -> float:
        return 1.0 / math.sqrt(self.var + EPSILON)

    def __call__(self, rewards: torch.Tensor, dones: torch.Tensor) -> torch.Tensor:
        """The normalised rewards of one step; ``dones`` ends the environments' discounted returns."""
        self.returns.mul_(self.gamma).add_(rewards)
        self._seen[self._steps] = self.returns
        self._steps += 1
        self.returns.masked_fill_(dones, 0.0)
        return (rewards * self.scale).clamp_(-self.clip, self.clip)

    def update(self) -> None:
        """Fold this iteration's returns, from all ranks, into the shared statistics (Chan et al.'s merge)."""
        seen = self._seen[: self._steps]
        self._steps = 0
        count, total, squares = self.comm.sum_values([seen.numel(), seen.sum().item(), seen.square().sum().item()])
        if not count:
            return
        batch_mean = total / count
        batch_var = max(squares / count - batch_mean**2, 0.0)
        combined = self.count + count
        delta = batch_mean - self.mean
        self.mean += delta * count / combined
        self.var = (self.var * self.count + batch_var * count + delta**2 * self.count * count / combined) / combined
        self.count = combined

    def common_state(self) -> dict:
        return {"count": self.count, "mean": self.mean, "var": self.var}

    def rank_state(self) -> torch.Tensor:
        return self.returns.clone()

    def load_state(self, common: dict, returns: torch.Tensor) -> None:
        self.count, self.mean, self.var = common["count"], common["mean"], common["var"]
        self.returns.copy_(returns)


def build_reward_normalizer(config: Config, comm: Comm) -> RewardNormalizer | None:
    """The normalizer ``config.reward`` asks for, if any."""
    if not config.reward.normalize:
        return None
    return RewardNormalizer(
        config.env.num_envs, config.num_steps_per_env, config.algorithm.gamma, config.reward.clip, comm
    )
