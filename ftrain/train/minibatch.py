"""The update's minibatches: which samples each step reads, and what it reads of them, worked out once per update.

What a minibatch step reads of the rollout alone (the observations through each model's normalizer, the advantages
normalised over the minibatch, the old log-probabilities) does not change while the models learn, so it is computed
once per minibatch, not once per epoch: with rsl-rl's one sample order for all epochs, every epoch visits the same
minibatches. At a minibatch of ~100 samples each tensor operation costs its overhead, not its arithmetic, and the
actor's rank of a split update paces the iteration, so the operations it does not repeat are its time saved.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import TYPE_CHECKING, NamedTuple

import torch
from rsl_rl.storage import RolloutStorage

from ftrain.policy.model import OBS_GROUP
from ftrain.train.split import Role

if TYPE_CHECKING:
    from ftrain.train.ppo import FusedPPO


class MiniBatch(NamedTuple):
    """What one minibatch step of the update reads; None where this rank's model does not read it (a split update)."""

    actor_obs: torch.Tensor | None
    """The observations through the actor's normalizer."""
    critic_obs: torch.Tensor | None
    """The observations through the critic's normalizer."""
    actions: torch.Tensor | None
    """The actions taken."""
    values: torch.Tensor | None
    """The critic's values when they were taken (for the clipped value loss)."""
    advantages: torch.Tensor | None
    """``[B]``, normalised over the minibatch where ``normalize_advantage_per_mini_batch``."""
    returns: torch.Tensor | None
    """The critic's targets."""
    old_log_prob: torch.Tensor | None
    """``[B]``: the actions' log-probability when they were taken."""
    old_mean: torch.Tensor | None
    """The action distribution when they were taken (the adaptive schedule's KL): its mean,"""
    old_std: torch.Tensor | None
    """and its standard deviation."""


def rollout_fields(storage: RolloutStorage) -> list[torch.Tensor]:
    """What the update reads of the storage, ``[steps, envs, d]`` each, in :class:`MiniBatch`'s order (the
    observations once, for both models)."""
    fields = [storage.observations[OBS_GROUP], storage.actions, storage.values, storage.advantages]
    return [*fields, storage.returns, storage.actions_log_prob, *storage.distribution_params]


def mini_batches(alg: FusedPPO, fields: list[torch.Tensor], orders: list[torch.Tensor]) -> Iterator[MiniBatch]:
    """rsl-rl's ``mini_batch_generator`` over ``fields`` (:func:`rollout_fields`, flat) in the sample order of each
    epoch (``orders``: one for all epochs, or one each), for the model ``alg``'s rank learns; in a split update, a team
    member gets its share of each minibatch."""
    current, batches = None, []
    for epoch in range(alg.num_learning_epochs):
        order = min(epoch, len(orders) - 1)
        if order != current:  # (an order of each epoch's own: its minibatches are made for it, and dropped after it)
            current, batches = order, [_mini_batch(alg, fields, rows) for rows in _epoch_rows(alg, orders[order])]
        yield from batches


def _epoch_rows(alg: FusedPPO, order: torch.Tensor) -> Iterator[torch.Tensor]:
    team, count = alg.team, alg.num_mini_batches
    size = order.numel() // count
    for start in range(0, size * count, size):
        rows = order[start : start + size]
        yield rows.tensor_split(team.size)[team.index] if team is not None and team.size > 1 else rows


def _mini_batch(alg: FusedPPO, fields: list[torch.Tensor], rows: torch.Tensor) -> MiniBatch:
    """The minibatch of ``rows``, with the fields the model this rank learns reads (the adaptive schedule's KL reads
    the old distribution too)."""
    role = alg.role
    used = {
        Role.ACTOR: frozenset({0, 1, 3, 5, *((6, 7) if alg.adaptive else ())}),
        Role.CRITIC: frozenset({0, 2, 4}),
        None: frozenset(range(len(fields))),
    }[role]
    obs, actions, values, advantages, returns, log_prob, old_mean, old_std = (
        field[rows] if index in used else None for index, field in enumerate(fields)
    )
    actor_obs = critic_obs = None
    with torch.no_grad():
        if role is not Role.CRITIC:
            actor_obs = alg.actor.obs_normalizer(obs)
            advantages, log_prob = advantages.squeeze(-1), log_prob.squeeze(-1)
            if alg.normalize_advantage_per_mini_batch:
                advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
        if role is not Role.ACTOR:
            critic_obs = alg.critic.obs_normalizer(obs)
    return MiniBatch(actor_obs, critic_obs, actions, values, advantages, returns, log_prob, old_mean, old_std)
