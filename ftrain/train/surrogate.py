"""PPO's actor loss for rsl-rl's Gaussian policy (a state-independent standard deviation) as one autograd node.

Why: the split update is paced by the actor's rank, and the actor's minibatch step was mostly the per-operation cost
of the twenty-odd small tensor operations between the policy's mean and the loss (docs/speed.md, "The split update's
balance"). Here the loss is a few operations forward and a few backward, its gradient written out: the
log-probability ``-|z|^2/2 - sum(log_std) - d log sqrt(2 pi)`` with ``z = (action - mean) / std``, and the entropy
``sum(log_std) + d (1/2 + log sqrt(2 pi))``, the same for every sample. Promises: rsl-rl's values to rounding
(``tests/train/test_surrogate.py``); a rank's share of a minibatch gives its share of the minibatch's mean (``batch``).
May import: torch.
"""

from __future__ import annotations

import math

import torch

LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))


class _ClippedSurrogate(torch.autograd.Function):
    @staticmethod
    def forward(ctx, mean, log_std, actions, advantages, old_log_prob, clip: float, entropy_coef: float, batch: int):
        # in place wherever a temporary allows: at a minibatch of ~100 samples the cost is per operation, not per number
        inv_std = log_std.neg().exp_()
        z = (actions - mean).mul_(inv_std)
        log_std_sum = log_std.sum()
        log_prob = z.square().sum(-1).mul_(-0.5).sub_(log_std_sum).sub_(mean.shape[-1] * LOG_SQRT_2PI)
        ratio = log_prob.sub_(old_log_prob).exp_()
        unclipped = advantages * ratio
        clipped = ratio.clamp_(1.0 - clip, 1.0 + clip).mul_(advantages)
        # d(surrogate)/d(log_prob) per sample: the ratio carries the gradient where the unclipped term is the smaller
        # one. Inside the clipping range both terms are equal, and autograd's max of rsl-rl's negated terms sends half
        # through each, all of it reaching the ratio; two terms that round equal outside it (a ratio an ulp past the
        # range) give the ratio all of it here and half under autograd: a difference of rounding's size
        through = unclipped <= clipped
        surrogate = torch.minimum(unclipped, clipped).sum().div_(batch).neg_()
        slope = unclipped.mul_(through).div_(-batch)
        share = mean.shape[0] / batch
        entropy = (log_std_sum + mean.shape[-1] * (0.5 + LOG_SQRT_2PI)) * share
        ctx.save_for_backward(z, inv_std, slope)
        ctx.entropy_weight = entropy_coef * share
        ctx.mark_non_differentiable(surrogate, entropy)
        return surrogate - entropy_coef * entropy, surrogate, entropy

    @staticmethod
    def backward(ctx, grad_loss, _surrogate, _entropy):
        z, inv_std, slope = ctx.saved_tensors
        weight = (slope * grad_loss).unsqueeze(-1)
        grad_mean = weight * z * inv_std
        grad_log_std = (weight * (z.square() - 1.0)).sum(0) - ctx.entropy_weight * grad_loss
        return grad_mean, grad_log_std, None, None, None, None, None, None


def clipped_surrogate(
    mean: torch.Tensor,
    log_std: torch.Tensor,
    actions: torch.Tensor,
    advantages: torch.Tensor,
    old_log_prob: torch.Tensor,
    clip: float,
    entropy_coef: float,
    batch: int | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """PPO's actor loss ``surrogate - entropy_coef * entropy`` of a minibatch, differentiable in ``mean`` ``[B, d]``
    and ``log_std`` ``[d]``; with the clipped surrogate loss and the mean entropy, for the logs. ``advantages`` and
    ``old_log_prob``: ``[B]``. ``batch``: the size of the whole minibatch, where these ``B`` samples are a rank's
    share of it (default ``B``): each term is then the share's part of the whole minibatch's mean."""
    batch = mean.shape[0] if batch is None else batch
    return _ClippedSurrogate.apply(mean, log_std, actions, advantages, old_log_prob, clip, entropy_coef, batch)
