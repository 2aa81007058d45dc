"""A ceiling on the action noise (``policy.final_noise_std``): it falls linearly from ``policy.init_noise_std`` at the
first iteration to ``final_noise_std`` at ``algorithm.schedule_iterations``, the learning rate's horizon; the learned
noise rules wherever it is lower.

Why: with no entropy bonus the learned noise shrinks slowly (Walker2d: from 0.7 to about 0.5 in 1M steps), so the
episodes trained on are those of a noisy policy while evaluation and users run its mean. A mean gait can lean a little
further each step and fall where the noisy ones did not, and training never sees that fall. A ceiling that closes in
keeps the noise of exploration early and trains on the episodes that will be played late (docs/learning.md).

It is rsl-rl's own clamp on the noise (the distribution's ``std_range``), moved before each rollout: a function of the
iteration alone, so the rollout and the update see the same noise, on every rank and in a resumed run; a policy
loaded from a checkpoint (``ftrain play --stochastic``) samples with the noise of its step. Imports: the config.
"""

from __future__ import annotations

import math

from rsl_rl.modules.distribution import GaussianDistribution

from ftrain.config import Config


class NoiseCeiling:
    def __init__(self, config: Config) -> None:
        self.initial = config.policy.init_noise_std
        self.final = config.policy.final_noise_std
        self.iterations = config.algorithm.schedule_iterations

    def at(self, iteration: int) -> float:
        """The ceiling of the rollout and update of iteration ``iteration + 1`` (``iteration`` completed so far)."""
        progress = min(1.0, iteration / self.iterations)
        return self.initial * (1 - progress) + self.final * progress

    def apply(self, distribution: GaussianDistribution, iteration: int) -> None:
        """Cap the noise of ``distribution`` (the actor's) for what comes after ``iteration`` completed iterations."""
        ceiling = self.at(iteration)
        distribution.std_range[1] = ceiling
        distribution.log_std_range[1] = math.log(ceiling)


def build_noise_ceiling(config: Config) -> NoiseCeiling | None:
    return NoiseCeiling(config) if config.policy.final_noise_std else None
