"""rsl-rl's algorithms built from an ftrain config; PPO with cheaper synchronisation and less per-step overhead.

rsl-rl's own multi-process update issues three collectives per minibatch (gradient all-reduce, KL all-reduce,
learning-rate broadcast) and three more per observation normalizer per iteration. :class:`FusedPPO` keeps the
same synchronous data-parallel PPO and changes only how it communicates:

- the KL rides in the gradient buffer, and every rank applies the adaptive learning-rate rule to the same global
  KL, which is what rank 0 would have broadcast: one collective per minibatch;
- on one machine that collective goes through shared memory (:mod:`ftrain.dist.shm_allreduce`), not loopback TCP,
  and across machines host first (:mod:`ftrain.dist.host_first`) (``shared_memory_all_reduce=false``: gloo);
- actor and critic normalize the same observations, so their statistics are reduced once, in two collectives;
- at an even number of ranks the update is split by model instead (``split_update``, ``ftrain.train.split``): the
  ranks gather the rollout into one global batch, the first half learns the actor and the second half the critic on
  all of it (data-parallel within a half), with Adam stepping only the weights that have gradients, and each half's
  first rank sends its model, Adam's state for it and the losses to all at the end. At two ranks that is one rank's
  update of the global batch bit for bit (the actor's gradients from its share of the loss are those from the whole
  loss), with 5 meetings per iteration instead of 44, and each rank learning one model instead of both; the adaptive
  schedule's KL goes from actor to critic at every minibatch without the actor waiting.

Its ``act`` computes what rsl-rl's does, on the one observation group ftrain's environments have, without the
TensorDict round trips; Adam runs as one fused kernel. The update computes rsl-rl's losses to rounding with fewer
operations: what a minibatch reads of the rollout is made once per update (``ftrain.train.minibatch``), and the
actor's loss is one autograd node (``ftrain.train.surrogate``), which brought the actor's minibatch step, the one a
split update waits for, from 1.32x the critic's to 1.18x (per rank, in training: docs/speed.md).
"""

from __future__ import annotations

import math

import torch
import torch.distributed as dist
from rsl_rl.algorithms import PPO, Distillation
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict
from torch import nn

from ftrain.config import Config
from ftrain.dist.group import RankInfo
from ftrain.dist.host_first import Collectives, build_collectives, hosts_of_ranks
from ftrain.policy.model import OBS_GROUP, build_actor, build_model, gaussian_log_std, gaussian_std
from ftrain.train.distillation import build_distillation
from ftrain.train.envs import MujocoVecEnv
from ftrain.train.minibatch import MiniBatch, mini_batches, rollout_fields
from ftrain.train.phases import Phases
from ftrain.train.split import Role, Team, adam_record, build_team, load_adam_record, record_size
from ftrain.train.surrogate import clipped_surrogate


class FusedPPO(PPO):
    """rsl-rl PPO (MLP policies) with one all-reduce per minibatch, over shared memory where ranks share a host."""

    def __init__(
        self,
        *args,
        reducer: Collectives | None = None,
        reshuffle_each_epoch: bool = False,
        phases: Phases | None = None,
        team: Team | None = None,
        **kwargs,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.reducer = reducer
        self.team = team
        """This rank's team in a split update (``ftrain.train.split``); None: data-parallel, or alone."""
        self.phases = phases or Phases()
        self.reshuffle_each_epoch = reshuffle_each_epoch
        self._actor_params = list(self.actor.parameters())
        self._critic_params = list(self.critic.parameters())
        self.optimizer = torch.optim.Adam(self._actor_params + self._critic_params, lr=self.learning_rate, fused=True)

    def act(self, obs: TensorDict) -> torch.Tensor:
        x = obs[OBS_GROUP]
        actor, critic = self._raw_actor, self._raw_critic
        distribution = actor.distribution
        distribution.update(actor.mlp(actor.obs_normalizer(x)))
        actions = distribution.sample()
        transition = self.transition
        transition.hidden_states = (None, None)
        transition.actions = actions
        transition.values = critic.mlp(critic.obs_normalizer(x))
        transition.actions_log_prob = distribution.log_prob(actions)
        transition.distribution_params = distribution.params
        transition.observations = obs
        return actions

    @property
    def role(self) -> Role | None:
        """The model this rank learns in a split update; None: both."""
        return self.team.role if self.team is not None else None

    @property
    def adaptive(self) -> bool:
        """rsl-rl's adaptive schedule: the learning rate follows every minibatch's KL."""
        return self.desired_kl is not None and self.schedule == "adaptive"

    def update(self) -> dict[str, float]:
        sums = {"value": 0.0, "surrogate": 0.0, "entropy": 0.0}
        learns_actor, learns_critic = self.role is not Role.CRITIC, self.role is not Role.ACTOR
        fields, orders = self._gathered_rollout() if self.role is not None else self._local_rollout()
        sends = []  # split update, adaptive schedule: the actor's KL of each minibatch, on its way to the critic
        for batch in mini_batches(self, fields, orders):
            if learns_actor:
                actor_loss, surrogate_loss, entropy, kl_mean = self._actor_terms(batch)
            if learns_critic:
                value_loss = self._value_loss(batch)
            if self.role is None:
                loss = actor_loss + self.value_loss_coef * value_loss
            elif learns_actor:  # the same gradients of the actor's weights as from the whole loss, bit for bit
                loss = actor_loss
            else:
                loss = self.value_loss_coef * value_loss

            self.optimizer.zero_grad()
            loss.backward()
            kl_mean = self._synchronise(kl_mean if learns_actor else None, sends)
            if self.adaptive:
                self._adapt_learning_rate(kl_mean)
            if learns_actor:
                nn.utils.clip_grad_norm_(self._actor_params, self.max_grad_norm)
            if learns_critic:
                nn.utils.clip_grad_norm_(self._critic_params, self.max_grad_norm)
            self.optimizer.step()  # Adam steps only the weights that have gradients: this rank's model

            if learns_critic:
                sums["value"] += value_loss.item()
            if learns_actor:
                sums["surrogate"] += surrogate_loss.item()
                sums["entropy"] += entropy.item()

        if self.role is not None:
            for send in sends:
                send.wait()
            sums = self._exchange_models(sums)
        self._update_normalizers(fields[0])
        self.storage.clear()
        num_updates = self.num_learning_epochs * self.num_mini_batches
        return {key: value / num_updates for key, value in sums.items()}

    def _actor_terms(self, batch: MiniBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The actor's loss of a minibatch, its clipped surrogate and entropy terms, and (adaptive schedule) its KL."""
        actor = self._raw_actor
        mean = actor.mlp(batch.actor_obs)
        log_std = gaussian_log_std(actor.distribution)
        loss, surrogate, entropy = clipped_surrogate(
            mean, log_std, batch.actions, batch.advantages, batch.old_log_prob, self.clip_param, self.entropy_coef
        )
        kl_mean = None
        if self.adaptive:
            with torch.inference_mode():
                new = (mean, gaussian_std(actor.distribution).expand_as(mean))
                kl_mean = torch.mean(actor.distribution.kl_divergence((batch.old_mean, batch.old_std), new))
        return loss, surrogate, entropy, kl_mean

    def _value_loss(self, batch: MiniBatch) -> torch.Tensor:
        values = self._raw_critic.mlp(batch.critic_obs)
        if self.use_clipped_value_loss:
            value_clipped = batch.values + (values - batch.values).clamp(-self.clip_param, self.clip_param)
            return torch.max((values - batch.returns).pow(2), (value_clipped - batch.returns).pow(2)).mean()
        return (batch.returns - values).pow(2).mean()

    def _synchronise(self, kl_mean: torch.Tensor | None, sends: list) -> torch.Tensor | None:
        """After a backward pass: gradients averaged over the ranks that share a model, and the KL the learning rate
        follows (``kl_mean``: this rank's actor's, adaptive schedule; a critic's rank receives its partner's)."""
        if self.is_multi_gpu and self.role is None:
            return self._all_reduce_mean(self._actor_params + self._critic_params, kl_mean)
        if self.team is not None and self.team.size > 1:
            own = self._actor_params if self.role is Role.ACTOR else self._critic_params
            reduced = self._all_reduce_mean(own, kl_mean, self.team)
            kl_mean = reduced if kl_mean is not None else None
        if kl_mean is not None and self.role is Role.ACTOR:  # the critic's learning rate follows the actor's KL
            sends.append(self.team.send_kl(kl_mean))
        elif self.role is Role.CRITIC and self.adaptive:
            with self.phases("sync_update"):
                kl_mean = self.team.receive_kl()
        return kl_mean

    def _local_rollout(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """This rank's rollout, flat (the one observation group as a plain tensor, no TensorDict indexing per
        minibatch), and the sample order of each epoch."""
        fields = rollout_fields(self.storage)
        return [field.flatten(0, 1) for field in fields], self._sample_orders(self.storage.num_envs)

    def _gathered_rollout(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Split update: every rank's rollout, environments in rank order (one global batch, as one rank with all
        the environments would hold it), in the sample order rank 0 drew. One all-gather per iteration."""
        fields = rollout_fields(self.storage)
        orders = self._sample_orders(self.storage.num_envs * self.gpu_world_size)  # every rank draws, alike
        every = self._all_gather(
            torch.cat([field.reshape(-1) for field in fields] + [order.float() for order in orders])
        )
        sizes = [field.numel() for field in fields] + [order.numel() for order in orders]
        per_rank = [torch.split(row, sizes) for row in every]
        gathered = [  # [steps, envs, d] of each rank -> [steps, envs of all ranks, d] -> [steps x all envs, d]
            torch.cat([parts[i].view(field.shape) for parts in per_rank], dim=1).flatten(0, 1)
            for i, field in enumerate(fields)
        ]
        return gathered, [order.long() for order in per_rank[0][len(fields) :]]

    def _sample_orders(self, num_envs: int) -> list[torch.Tensor]:
        """The sample order of each epoch, drawn up front (nothing else draws during the update): rsl-rl draws one
        permutation for all epochs, so every epoch visits the same minibatches in the same order; with
        ``reshuffle_each_epoch`` each epoch draws its own, as SB3 and most PPOs do."""
        count = num_envs * self.storage.num_transitions_per_env
        return [torch.randperm(count) for _ in range(self.num_learning_epochs if self.reshuffle_each_epoch else 1)]

    def _all_reduce_mean(
        self, params: list[nn.Parameter], kl_mean: torch.Tensor | None, team: Team | None = None
    ) -> torch.Tensor | None:
        """Average every gradient (and the KL, riding in the same buffer) over all ranks, or over ``team``, in place."""
        grads = [p.grad.view(-1) for p in params if p.grad is not None]
        extra = [kl_mean.view(1).to(grads[0].dtype)] if kl_mean is not None else []
        ranks = team.size if team is not None else self.gpu_world_size
        packed = self._sum_over_ranks(torch.cat(grads + extra), team).div_(ranks)
        offset = 0
        for grad in grads:
            grad.copy_(packed[offset : offset + grad.numel()])
            offset += grad.numel()
        return packed[offset] if kl_mean is not None else None

    def _sum_over_ranks(self, tensor: torch.Tensor, team: Team | None = None) -> torch.Tensor:
        """In place, over all ranks or over ``team``: through shared memory where it has some, else gloo."""
        reducer, group = (team.reducer, team.group) if team is not None else (self.reducer, None)
        with self.phases("sync_update"):
            if reducer is not None:
                return reducer.all_reduce_(tensor)
            dist.all_reduce(tensor, group=group)
            return tensor

    def _all_gather(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` in rank order, ``[world, n]``."""
        with self.phases("sync_update"):
            if self.reducer is not None and tensor.numel() <= self.reducer.capacity:
                return self.reducer.all_gather(tensor)
            every = [torch.empty_like(tensor) for _ in range(self.gpu_world_size)]
            dist.all_gather(every, tensor)
            return torch.stack(every)

    def _broadcast(self, tensor: torch.Tensor, src: int) -> None:
        """Rank ``src``'s ``tensor`` on every rank, in place: through shared memory where it fits, else gloo."""
        if self.reducer is not None and tensor.numel() <= self.reducer.broadcast_capacity:
            self.reducer.broadcast_(tensor, src)
        else:
            dist.broadcast(tensor, src=src)

    def _exchange_models(self, sums: dict[str, float]) -> dict[str, float]:
        """Split update: each team's first rank sends the model the team learned (weights, Adam's moments and step
        counts) with the team's losses to every rank, so all end the update with the same state, as after a
        data-parallel one."""
        team = self.team
        mine = torch.tensor(list(sums.values()))
        if team.size > 1:  # the mean over the members' shares
            mine = self._sum_over_ranks(mine, team) / team.size
        losses = {}
        with self.phases("sync_update"):
            for role, params in ((Role.ACTOR, self._actor_params), (Role.CRITIC, self._critic_params)):
                ours = role is team.role
                if ours:
                    record = torch.cat([mine, adam_record(self.optimizer, params)])
                else:
                    record = torch.empty(len(sums) + record_size(params))
                self._broadcast(record, (team.ranks if ours else team.other)[0])
                if not ours:
                    load_adam_record(self.optimizer, params, record[len(sums) :])
                losses[role] = dict(zip(sums, record[: len(sums)].tolist(), strict=True))
        actor, critic = losses[Role.ACTOR], losses[Role.CRITIC]
        return {"value": critic["value"], "surrogate": actor["surrogate"], "entropy": actor["entropy"]}

    def _update_normalizers(self, obs: torch.Tensor) -> None:
        """rsl-rl's ``EmpiricalNormalization.update`` for actor and critic at once, from global batch moments.

        Alone, each normalizer computes the moments itself; across ranks it would all-reduce three times, and
        twice over. Here the global mean and variance are reduced once (two rounds, as rsl-rl's formula needs the
        global mean before the variance around it; the count rides with the mean) and applied to both with rsl-rl's
        update rule.
        """
        normalizers = [m.obs_normalizer for m in (self.actor, self.critic) if m.obs_normalization]
        if not normalizers or not normalizers[0].training:
            return
        if not self.is_multi_gpu:
            for normalizer in normalizers:
                normalizer.update(obs)
            return
        count = obs.shape[0]
        mean = obs.mean(dim=0, keepdim=True)
        var = obs.var(dim=0, unbiased=False, keepdim=True)
        if self.role is None:  # data-parallel: this rank's share of the batch; a split update holds all of it
            sums = self._sum_over_ranks(torch.cat([(mean * count).view(-1), torch.tensor([count * 1.0])]))
            local_count, local_mean, local_var = count, mean, var
            count = round(sums[-1].item())
            mean = (sums[:-1] / count).view(1, -1)
            var = self._sum_over_ranks(local_count * (local_var + (local_mean - mean).square())) / count
        count_x = torch.tensor(count, dtype=torch.long)
        for normalizer in normalizers:
            normalizer.count += count_x
            rate = count_x / normalizer.count
            delta_mean = mean - normalizer._mean
            normalizer._mean += rate * delta_mean
            normalizer._var += rate * (var - normalizer._var + delta_mean * (mean - normalizer._mean))
            normalizer._std = torch.sqrt(normalizer._var)

    def _adapt_learning_rate(self, kl_mean: torch.Tensor) -> None:
        """rsl-rl's adaptive schedule; every rank computes it from the same global KL, so no broadcast is needed."""
        if kl_mean > self.desired_kl * 2.0:
            self.learning_rate = max(1e-5, self.learning_rate / 1.5)
        elif kl_mean < self.desired_kl / 2.0 and kl_mean > 0.0:
            self.learning_rate = min(1e-2, self.learning_rate * 1.5)
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate


def build_ppo(config: Config, env: MujocoVecEnv, info: RankInfo, phases: Phases | None = None) -> FusedPPO:
    obs = env.get_observations()
    actor = build_actor(config, obs, env.num_actions)
    critic = build_model(config, obs, "critic", 1)
    storage = RolloutStorage("rl", env.num_envs, config.num_steps_per_env, obs, [env.num_actions])
    a = config.algorithm
    sizes = [[p.numel() for p in model.parameters()] for model in (actor, critic)]
    hosts = hosts_of_ranks(info) if config.shared_memory_all_reduce and info.distributed else None
    team = build_team(config, info, max(map(sum, sizes)) + 1, hosts)
    capacity = sum(map(sum, sizes)) + 1  # data-parallel: the gradients of both models and the KL
    if team is not None:  # gathers the rollout and its sample orders instead, and broadcasts the models
        samples = env.num_envs * config.num_steps_per_env
        draws = a.num_learning_epochs if a.reshuffle_each_epoch else 1
        record = 3 + max(record_size(list(model.parameters())) for model in (actor, critic))
        rollout = samples * (env.num_obs + 3 * env.num_actions + 4 + 2 * draws)
        capacity = max(rollout, math.ceil(record / info.world_size))  # a broadcast carries world x capacity
    reducer = build_collectives(info, capacity, config.dist_timeout, hosts)
    return FusedPPO(
        actor,
        critic,
        storage,
        num_learning_epochs=a.num_learning_epochs,
        num_mini_batches=a.num_mini_batches,
        clip_param=a.clip_param,
        gamma=a.gamma,
        lam=a.lam,
        value_loss_coef=a.value_loss_coef,
        entropy_coef=a.entropy_coef,
        learning_rate=a.learning_rate,
        max_grad_norm=a.max_grad_norm,
        use_clipped_value_loss=a.use_clipped_value_loss,
        schedule=a.schedule,
        desired_kl=a.desired_kl,
        normalize_advantage_per_mini_batch=a.normalize_advantage_per_mini_batch,
        multi_gpu_cfg=info.rsl_rl_cfg(),
        reducer=reducer,
        reshuffle_each_epoch=a.reshuffle_each_epoch,
        phases=phases,
        team=team,
    )


def build_algorithm(
    config: Config, env: MujocoVecEnv, info: RankInfo, phases: Phases | None = None
) -> PPO | Distillation:
    """``phases``: where PPO's update charges its all-reduces (rsl-rl's Distillation keeps them in its update)."""
    if config.algorithm.class_name == "Distillation":
        return build_distillation(config, env, info)
    return build_ppo(config, env, info, phases)


def load_learned_state(alg: PPO | Distillation, state: dict, learning_rate: float) -> None:
    """Models (with normalizers) and optimizer from rsl-rl's keys in ``state``; the adaptive learning rate."""
    alg.load(state, load_cfg=None, strict=True)
    alg.learning_rate = learning_rate
    for group in alg.optimizer.param_groups:
        group["lr"] = learning_rate
