"""The update's minibatches: which samples of the global batch each step reads, which of them this rank learns from,
and what it reads of them, worked out once per update.

Owns the rule that makes the world size no hyperparameter: every minibatch is drawn from the global batch (every
rank's environments, in the order one rank holding all of them would store them) with the run's shared sample order,
its advantages are normalised over the whole minibatch, and a rank's losses are its samples' share of the
minibatch's mean (their sum over the minibatch's size), so that the ranks' summed gradients are one rank's. A rank
learns from the samples it holds (data-parallel: its own environments') or from its member's share of every
minibatch (a split update's team). What a step reads of the rollout alone (observations through the normalizers,
normalised advantages) does not change while the models learn, so it is made once per update, not once per epoch.

May import: ``ftrain.policy.model``, ``ftrain.train.split``, torch and rsl-rl (not ``ppo.py``, which uses it).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import torch
from rsl_rl.storage import RolloutStorage
from torch import nn

from ftrain.policy.model import OBS_GROUP
from ftrain.train.split import Role, Team


class Learner(Protocol):
    """What the minibatches read of the algorithm (``ftrain.train.ppo.FusedPPO`` is one)."""

    num_learning_epochs: int
    num_mini_batches: int
    per_minibatch_advantages: bool
    team: Team | None
    actor: nn.Module
    critic: nn.Module

    @property
    def role(self) -> Role | None: ...

    @property
    def adaptive(self) -> bool: ...


class MiniBatch(NamedTuple):
    """What one minibatch step of a rank reads; None where its model does not read it (a split update)."""

    size: int
    """The samples of the whole minibatch, of all ranks: a rank's losses are its samples' sum over it."""
    actor_obs: torch.Tensor | None
    """The observations through the actor's normalizer."""
    critic_obs: torch.Tensor | None
    """The observations through the critic's normalizer."""
    actions: torch.Tensor | None
    """The actions taken."""
    values: torch.Tensor | None
    """The critic's values when they were taken (for the clipped value loss)."""
    advantages: torch.Tensor | None
    """``[B]``, normalised over the whole minibatch (``normalize_advantage_per_mini_batch``) or the whole batch."""
    returns: torch.Tensor | None
    """The critic's targets."""
    old_log_prob: torch.Tensor | None
    """``[B]``: the actions' log-probability when they were taken."""
    old_mean: torch.Tensor | None
    """The action distribution when they were taken (the adaptive schedule's KL): its mean,"""
    old_std: torch.Tensor | None
    """and its standard deviation."""


@dataclass(frozen=True)
class Rollout:
    """The iteration's rollout as the update reads it."""

    fields: list[torch.Tensor]
    """The samples this rank holds, flat, in :func:`rollout_fields`'s order."""
    advantages: torch.Tensor
    """``[samples]``: the advantages of the global batch (every rank's), flat, in the global order."""
    envs: int
    """The environments whose samples this rank holds: its own (data-parallel), or all of them."""
    first_env: int
    """The global index of the first of them."""
    total_envs: int
    """The environments of all ranks."""

    @property
    def samples(self) -> int:
        return self.advantages.numel()

    def held(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Of the global batch's ``rows``, those this rank holds: their global indices and where it holds them.
        (Global row ``step x total_envs + env``, as one rank with every environment stores its rollout.)"""
        if self.envs == self.total_envs:
            return rows, rows
        step, env = rows.div(self.total_envs, rounding_mode="floor"), rows.remainder(self.total_envs) - self.first_env
        mine = (env >= 0) & (env < self.envs)
        return rows[mine], step[mine] * self.envs + env[mine]


def rollout_fields(storage: RolloutStorage) -> list[torch.Tensor]:
    """What the update reads of the storage, ``[steps, envs, d]`` each, in :class:`MiniBatch`'s order (the
    observations once, for both models)."""
    fields = [storage.observations[OBS_GROUP], storage.actions, storage.values, storage.advantages]
    return [*fields, storage.returns, storage.actions_log_prob, *storage.distribution_params]


def mini_batches(alg: Learner, rollout: Rollout, orders: list[torch.Tensor]) -> Iterator[MiniBatch]:
    """rsl-rl's ``mini_batch_generator`` over the global batch in the sample order of each epoch (``orders``: one for
    all epochs, or one each), for the model ``alg``'s rank learns, from the samples it learns from."""
    advantages = rollout.advantages
    if not alg.per_minibatch_advantages:  # over the whole batch, as rsl-rl's compute_returns does on one rank
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    current, batches = None, []
    for epoch in range(alg.num_learning_epochs):
        order = min(epoch, len(orders) - 1)
        if order != current:  # (an order of each epoch's own: its minibatches are made for it, and dropped after it)
            rows = _epoch_rows(orders[order], alg.num_mini_batches)
            current, batches = order, [_mini_batch(alg, rollout, advantages, each) for each in rows]
        yield from batches


def _epoch_rows(order: torch.Tensor, count: int) -> Iterator[torch.Tensor]:
    size = order.numel() // count
    for start in range(0, size * count, size):
        yield order[start : start + size]


def _mini_batch(alg: Learner, rollout: Rollout, advantages: torch.Tensor, rows: torch.Tensor) -> MiniBatch:
    """The minibatch of the global ``rows``: of the samples this rank learns from, the fields its model reads (the
    adaptive schedule's KL reads the old distribution too)."""
    role, team = alg.role, alg.team
    mine = rows.tensor_split(team.size)[team.index] if team is not None and team.size > 1 else rows
    mine, local = rollout.held(mine)
    used = {
        Role.ACTOR: frozenset({0, 1, 5, *((6, 7) if alg.adaptive else ())}),
        Role.CRITIC: frozenset({0, 2, 4}),
        None: frozenset(range(len(rollout.fields))),
    }[role]
    obs, actions, values, _, returns, log_prob, old_mean, old_std = (
        field[local] if index in used else None for index, field in enumerate(rollout.fields)
    )
    actor_obs = critic_obs = ours = None
    with torch.no_grad():
        if role is not Role.CRITIC:
            actor_obs = alg.actor.obs_normalizer(obs)
            log_prob = log_prob.squeeze(-1)
            ours = advantages[mine]
            if alg.per_minibatch_advantages:
                whole = advantages[rows]
                ours = (ours - whole.mean()) / (whole.std() + 1e-8)
        if role is not Role.ACTOR:
            critic_obs = alg.critic.obs_normalizer(obs)
    return MiniBatch(rows.numel(), actor_obs, critic_obs, actions, values, ours, returns, log_prob, old_mean, old_std)
