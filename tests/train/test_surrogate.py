"""The actor's loss as one autograd node (ftrain.train.surrogate) against rsl-rl's Gaussian distribution under
autograd: the same loss, clipped surrogate, entropy and gradients, to rounding, with samples inside and outside the
clipping range and advantages of both signs."""

from __future__ import annotations

import pytest
import torch
from rsl_rl.modules.distribution import GaussianDistribution

from ftrain.config import load_config
from ftrain.policy.model import action_std, build_actor, gaussian_log_std
from ftrain.train.envs import MujocoVecEnv
from ftrain.train.surrogate import clipped_surrogate

from helpers import SMOKE

CLIP, ENTROPY_COEF = 0.2, 0.01


def rsl_rl_loss(distribution: GaussianDistribution, mean, actions, advantages, old_log_prob):
    """rsl-rl's PPO actor terms, as its update computes them."""
    distribution.update(mean)
    ratio = torch.exp(distribution.log_prob(actions) - old_log_prob)
    surrogate = torch.max(-advantages * ratio, -advantages * torch.clamp(ratio, 1.0 - CLIP, 1.0 + CLIP)).mean()
    entropy = distribution.entropy.mean()
    return surrogate - ENTROPY_COEF * entropy, surrogate, entropy


@pytest.mark.parametrize("std_type", ["log", "scalar"])
def test_loss_and_gradients_are_rsl_rl_s(std_type: str) -> None:
    generator = torch.Generator().manual_seed(0)
    samples, dims = 256, 6
    distribution = GaussianDistribution(dims, init_std=0.4, std_type=std_type)
    with torch.no_grad():  # a standard deviation per dimension, not the initial one everywhere
        param = distribution.log_std_param if std_type == "log" else distribution.std_param
        param.mul_(torch.linspace(0.5, 1.5, dims))
    mean = torch.randn(samples, dims, generator=generator, dtype=torch.float64).float().requires_grad_()
    actions = mean.detach() + 0.4 * torch.randn(samples, dims, generator=generator)
    advantages = torch.randn(samples, generator=generator)
    with torch.no_grad():  # log-probabilities of a slightly different policy: ratios on both sides of the clip range
        distribution.update(mean + 0.1 * torch.randn(samples, dims, generator=generator))
        old_log_prob = distribution.log_prob(actions)
        distribution.update(mean)
        ratio = torch.exp(distribution.log_prob(actions) - old_log_prob)
    outside = (ratio < 1 - CLIP) | (ratio > 1 + CLIP)
    assert 0.1 < outside.float().mean() < 0.9, "the samples must exercise the clipping both ways"

    theirs = rsl_rl_loss(distribution, mean, actions, advantages, old_log_prob)
    their_grads = torch.autograd.grad(theirs[0], [mean, param])
    ours = clipped_surrogate(
        mean, gaussian_log_std(distribution), actions, advantages, old_log_prob, CLIP, ENTROPY_COEF
    )
    our_grads = torch.autograd.grad(ours[0], [mean, param])
    for name, mine, reference in zip(("loss", "surrogate", "entropy"), ours, theirs, strict=True):
        assert mine.item() == pytest.approx(reference.item(), rel=1e-5, abs=1e-7), name
    for name, mine, reference in zip(("mean", "std parameter"), our_grads, their_grads, strict=True):
        assert reference.abs().max() > 0, name
        torch.testing.assert_close(mine, reference, rtol=1e-4, atol=1e-8, msg=f"gradient of the {name}")


@pytest.mark.parametrize("std_type", ["log", "scalar"])
def test_the_logged_action_std_is_the_policy_s_now_not_the_last_batch_s(std_type: str) -> None:
    """The update no longer passes its minibatches through the distribution, so ``distribution.std`` keeps the last
    rollout step's: the metric reads the parameter (after the update's last step)."""
    config = load_config(SMOKE, [f"policy.std_type={std_type}"])
    env = MujocoVecEnv(config.env.id, config.env.num_envs, seed=0, kwargs=config.env.kwargs)
    actor = build_actor(config, env.get_observations(), env.num_actions)
    distribution = actor.distribution
    distribution.update(torch.zeros(4, env.num_actions))  # a batch seen before the parameter moves
    param = distribution.log_std_param if std_type == "log" else distribution.std_param
    with torch.no_grad():  # a learned standard deviation, away from the initial one
        learned = torch.linspace(0.2, 0.4, env.num_actions)
        param.copy_(learned.log() if std_type == "log" else learned)
    expected = (param.exp() if std_type == "log" else param).mean().item()
    assert action_std(actor) == pytest.approx(expected, rel=1e-6)
    assert actor.output_std.mean().item() != pytest.approx(expected, rel=1e-3), "the last batch's std is stale"
