"""Reward normalisation: rewards scaled by the std of the discounted returns seen in earlier iterations, clipped,
and its state restored exactly."""

from __future__ import annotations

import numpy as np
import torch

from ftrain.comm.collectives import Comm, Traffic
from ftrain.comm.group import RankInfo
from ftrain.train.reward_norm import EPSILON, RewardNormalizer

ALONE = Comm.build(RankInfo(0, 1, 0), Traffic(per_rank=1), timeout_s=1, shared_memory=False, say=print)
GAMMA = 0.9


def steps(iterations: int, num_envs: int = 3, num_steps: int = 4, seed: int = 0):
    """(iteration, rewards, dones) of a made-up rollout; env 1 ends an episode at every third step."""
    generator = torch.Generator().manual_seed(seed)
    for iteration in range(iterations):
        for step in range(num_steps):
            dones = torch.zeros(num_envs, dtype=torch.bool)
            dones[1] = step % 3 == 2
            yield iteration, torch.randn(num_envs, generator=generator) * 5 + 1, dones


def test_rewards_are_divided_by_the_std_of_the_discounted_returns_of_earlier_iterations() -> None:
    normalizer = RewardNormalizer(3, 4, GAMMA, clip=10.0, comm=ALONE)
    returns, seen, current, scale = np.zeros(3), [], 0, 1.0  # unscaled until there are statistics
    for iteration, rewards, dones in steps(5):
        if iteration != current:  # the statistics move at iteration boundaries only
            normalizer.update()
            current, scale = iteration, 1 / np.sqrt(np.var(seen) + EPSILON)
        scaled = normalizer(rewards, dones)
        returns = returns * GAMMA + rewards.numpy()
        seen.extend(returns)
        returns[dones.numpy()] = 0
        assert torch.allclose(scaled, rewards * scale)
    normalizer.update()
    assert normalizer.count == len(seen) == 60
    assert np.isclose(normalizer.mean, np.mean(seen)) and np.isclose(normalizer.var, np.var(seen))


def test_normalised_rewards_are_clipped() -> None:
    normalizer = RewardNormalizer(2, 1, GAMMA, clip=3.0, comm=ALONE)
    normalizer(torch.tensor([1.0, -1.0]), torch.zeros(2, dtype=torch.bool))
    normalizer.update()
    scaled = normalizer(torch.tensor([100.0, -100.0]), torch.zeros(2, dtype=torch.bool))
    assert scaled.tolist() == [3.0, -3.0]


def run(normalizer: RewardNormalizer, rollout: list) -> list[torch.Tensor]:
    """The scaled rewards of ``rollout`` (from ``steps``), updating the statistics at each iteration's end."""
    scaled = []
    for index, (iteration, rewards, dones) in enumerate(rollout):
        scaled.append(normalizer(rewards, dones))
        if index + 1 == len(rollout) or rollout[index + 1][0] != iteration:
            normalizer.update()
    return scaled


def test_state_restores_exactly() -> None:
    rollout = list(steps(6))
    original = RewardNormalizer(3, 4, GAMMA, clip=10.0, comm=ALONE)
    run(original, rollout[:12])
    restored = RewardNormalizer(3, 4, GAMMA, clip=10.0, comm=ALONE)
    restored.load_state(original.common_state(), original.rank_state())
    for ours, theirs in zip(run(restored, rollout[12:]), run(original, rollout[12:]), strict=True):
        assert torch.equal(ours, theirs)
    assert restored.common_state() == original.common_state()
    assert torch.equal(restored.rank_state(), original.rank_state())
