"""rsl-rl's PPO built from an ftrain config, as one rank's update of the global batch at any number of ranks.

Owns what the world size must not change: the same rollouts (the action noise of environment ``g`` is row ``g`` of
a draw from the run's shared generator, the same on every rank; the environments are seeded by global index in the
trainer) and the same update (minibatches of the global batch in the shared sample order, ``ftrain.train.minibatch``),
so N ranks x E environments train what 1 rank x N·E trains, to rounding. Two ways to share the update:

- data-parallel: a rank learns both models from the samples it holds, its losses being their share of each global
  minibatch, and the gradients are summed over the ranks (the KL and the losses ride in the same buffer);
- split (``split_update``, an even number of ranks, ``ftrain.train.split``): the rollout is gathered, the first half
  of the ranks learns the actor and the second half the critic on all of it (each team data-parallel over shares of
  every minibatch), Adam steps only the weights with gradients, and each team's first rank sends its model and Adam's
  state for it to all at the end; the critic's learning rate follows the actor's KL, sent to it per minibatch.

Every collective goes through ``ftrain.comm.collectives.Comm``, sized here from what is sent. ``act`` computes rsl-rl's
on the one observation group ftrain's environments have; the actor's loss is one autograd node
(``ftrain.train.surrogate``); Adam runs as one fused kernel.

May import: ``ftrain.comm``, ``ftrain.policy.model``, ``ftrain.train``'s update modules, torch and rsl-rl.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from rsl_rl.algorithms import PPO, Distillation
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict
from torch import nn

from ftrain.comm.collectives import Comm, Traffic
from ftrain.comm.group import RankInfo, run_seed
from ftrain.config import Config
from ftrain.policy.model import OBS_GROUP, build_actor, build_model, gaussian_log_std, gaussian_std
from ftrain.train.distillation import build_distillation
from ftrain.train.envs import MujocoVecEnv
from ftrain.train.minibatch import MiniBatch, Rollout, mini_batches, rollout_fields
from ftrain.train.phases import Phases
from ftrain.train.split import Role, Team, adam_record, build_team, load_adam_record, record_size, splits_update
from ftrain.train.surrogate import clipped_surrogate

SMALL_GATHERS = 256
"""float32 elements per rank that the iteration's small gathers carry at most (metrics, votes, reward statistics)."""


class FusedPPO(PPO):
    """rsl-rl PPO (MLP policies): one rank's update of the global batch, on any number of ranks."""

    def __init__(
        self,
        *args,
        comm: Comm,
        shared_seed: int = 0,
        reshuffle_each_epoch: bool = False,
        normalize_advantage_per_mini_batch: bool = False,
        phases: Phases | None = None,
        team: Team | None = None,
        **kwargs,
    ) -> None:
        # rsl-rl would normalise the advantages over this rank's rollout alone: here the update does, over all ranks'
        super().__init__(*args, normalize_advantage_per_mini_batch=True, **kwargs)
        self.per_minibatch_advantages = normalize_advantage_per_mini_batch
        self.comm = comm
        """The collectives of all ranks."""
        self.team = team
        """This rank's team in a split update (``ftrain.train.split``); None: data-parallel, or alone."""
        self.shared_generator = torch.Generator().manual_seed(shared_seed)
        """The run's random stream for the action noise and the sample orders: the same on every rank."""
        self.phases = phases or Phases()
        self.reshuffle_each_epoch = reshuffle_each_epoch
        self.first_env = self.gpu_global_rank * self.storage.num_envs
        """This rank's first environment's global index."""
        self.total_envs = self.gpu_world_size * self.storage.num_envs
        self._actor_params = list(self.actor.parameters())
        self._critic_params = list(self.critic.parameters())
        self.optimizer = torch.optim.Adam(self._actor_params + self._critic_params, lr=self.learning_rate, fused=True)

    def act(self, obs: TensorDict) -> torch.Tensor:
        x = obs[OBS_GROUP]
        actor, critic = self._raw_actor, self._raw_critic
        distribution = actor.distribution
        mean = actor.mlp(actor.obs_normalizer(x))
        distribution.update(mean)
        # rsl-rl's sample (torch.normal(mean, std) is mean + std x standard noise, bit for bit), with the noise of
        # every environment of the run drawn alike on every rank and this rank's rows taken
        noise = torch.randn((self.total_envs, mean.shape[1]), generator=self.shared_generator)
        actions = mean + gaussian_std(distribution) * noise[self.first_env : self.first_env + mean.shape[0]]
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
        rollout = self._gathered_rollout() if self.role is not None else self._local_rollout()
        sends = []  # split update, adaptive schedule: the actor's KL of each minibatch, on its way to the critic
        for batch in mini_batches(self, rollout, self._sample_orders(rollout.samples)):
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
        elif self.comm.size > 1:  # each rank's sums are its shares of the minibatches' means
            sums = dict(zip(sums, self._sum_over_ranks(torch.tensor(list(sums.values()))).tolist(), strict=True))
        self._update_normalizers(rollout.fields[0])
        self.storage.clear()
        num_updates = self.num_learning_epochs * self.num_mini_batches
        return {key: value / num_updates for key, value in sums.items()}

    def _actor_terms(self, batch: MiniBatch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """This rank's share of the actor's loss of a minibatch, of its clipped surrogate and entropy terms, and
        (adaptive schedule) of its KL."""
        actor = self._raw_actor
        mean = actor.mlp(batch.actor_obs)
        log_std = gaussian_log_std(actor.distribution)
        loss, surrogate, entropy = clipped_surrogate(
            mean,
            log_std,
            batch.actions,
            batch.advantages,
            batch.old_log_prob,
            self.clip_param,
            self.entropy_coef,
            batch.size,
        )
        kl_mean = None
        if self.adaptive:
            with torch.inference_mode():
                new = (mean, gaussian_std(actor.distribution).expand_as(mean))
                kl_mean = actor.distribution.kl_divergence((batch.old_mean, batch.old_std), new).sum() / batch.size
        return loss, surrogate, entropy, kl_mean

    def _value_loss(self, batch: MiniBatch) -> torch.Tensor:
        """This rank's share of the critic's loss of a minibatch."""
        values = self._raw_critic.mlp(batch.critic_obs)
        if self.use_clipped_value_loss:
            value_clipped = batch.values + (values - batch.values).clamp(-self.clip_param, self.clip_param)
            errors = torch.max((values - batch.returns).pow(2), (value_clipped - batch.returns).pow(2))
        else:
            errors = (batch.returns - values).pow(2)
        return errors.sum() / batch.size

    def _synchronise(self, kl_mean: torch.Tensor | None, sends: list) -> torch.Tensor | None:
        """After a backward pass: gradients summed over the ranks that share a model, and the KL the learning rate
        follows (``kl_mean``: this rank's share of the actor's, adaptive schedule; a critic's rank receives its
        partner's)."""
        if self.comm.size > 1 and self.role is None:
            return self._all_reduce(self._actor_params + self._critic_params, kl_mean, self.comm)
        if self.team is not None and self.team.size > 1:
            own = self._actor_params if self.role is Role.ACTOR else self._critic_params
            reduced = self._all_reduce(own, kl_mean, self.team.comm)
            kl_mean = reduced if kl_mean is not None else None
        if kl_mean is not None and self.role is Role.ACTOR:  # the critic's learning rate follows the actor's KL
            sends.append(self.team.send_kl(kl_mean))
        elif self.role is Role.CRITIC and self.adaptive:
            with self.phases("sync_update"):
                kl_mean = self.team.receive_kl()
        return kl_mean

    def _local_rollout(self) -> Rollout:
        """This rank's rollout, flat (the one observation group as a plain tensor, no TensorDict indexing per
        minibatch), and the advantages of all ranks (data-parallel: one all-gather per iteration)."""
        fields = [field.flatten(0, 1) for field in rollout_fields(self.storage)]
        advantages = self.storage.advantages.squeeze(-1)  # [steps, envs]
        if self.comm.size > 1:  # [ranks, steps x envs] -> [steps, ranks, envs]: in the global order
            every = self._all_gather(advantages.reshape(-1)).view(self.gpu_world_size, *advantages.shape)
            advantages = every.transpose(0, 1)
        envs = self.storage.num_envs
        return Rollout(fields, advantages.reshape(-1), envs, self.first_env, self.total_envs)

    def _gathered_rollout(self) -> Rollout:
        """Split update: every rank's rollout, environments in rank order (one global batch, as one rank with all
        the environments would hold it). One all-gather per iteration."""
        fields = rollout_fields(self.storage)
        every = self._all_gather(torch.cat([field.reshape(-1) for field in fields]))
        per_rank = [torch.split(row, [field.numel() for field in fields]) for row in every]
        gathered = [  # [steps, envs, d] of each rank -> [steps, envs of all ranks, d] -> [steps x all envs, d]
            torch.cat([parts[i].view(field.shape) for parts in per_rank], dim=1).flatten(0, 1)
            for i, field in enumerate(fields)
        ]
        return Rollout(gathered, gathered[3].squeeze(-1), self.total_envs, 0, self.total_envs)

    def _sample_orders(self, samples: int) -> list[torch.Tensor]:
        """The sample order of each epoch, drawn up front from the shared generator (every rank draws alike, so no
        order is sent): rsl-rl draws one permutation for all epochs, so every epoch visits the same minibatches in
        the same order; with ``reshuffle_each_epoch`` each epoch draws its own, as SB3 and most PPOs do."""
        draws = self.num_learning_epochs if self.reshuffle_each_epoch else 1
        return [torch.randperm(samples, generator=self.shared_generator) for _ in range(draws)]

    def _all_reduce(self, params: list[nn.Parameter], kl_mean: torch.Tensor | None, comm: Comm) -> torch.Tensor | None:
        """Sum every gradient (and the KL, riding in the same buffer) over ``comm``'s ranks, in place."""
        grads = [p.grad.view(-1) for p in params if p.grad is not None]
        extra = [kl_mean.view(1).to(grads[0].dtype)] if kl_mean is not None else []
        packed = self._sum_over_ranks(torch.cat(grads + extra), comm)
        offset = 0
        for grad in grads:
            grad.copy_(packed[offset : offset + grad.numel()])
            offset += grad.numel()
        return packed[offset] if kl_mean is not None else None

    def _sum_over_ranks(self, tensor: torch.Tensor, comm: Comm | None = None) -> torch.Tensor:
        """In place, over all ranks or over ``comm``'s."""
        with self.phases("sync_update"):
            return (comm or self.comm).all_reduce_sum_(tensor)

    def _all_gather(self, tensor: torch.Tensor) -> torch.Tensor:
        """Every rank's ``tensor`` in rank order, ``[world, n]``."""
        with self.phases("sync_update"):
            return self.comm.all_gather(tensor)

    def _exchange_models(self, sums: dict[str, float]) -> dict[str, float]:
        """Split update: each team's first rank sends the model the team learned (weights, Adam's moments and step
        counts) with the team's losses to every rank, so all end the update with the same state, as after a
        data-parallel one."""
        team = self.team
        mine = torch.tensor(list(sums.values()))
        if team.size > 1:  # the members' shares of the minibatches' means
            mine = self._sum_over_ranks(mine, team.comm)
        losses = {}
        with self.phases("sync_update"):
            for role, params in ((Role.ACTOR, self._actor_params), (Role.CRITIC, self._critic_params)):
                ours = role is team.role
                if ours:
                    record = torch.cat([mine, adam_record(self.optimizer, params)])
                else:
                    record = torch.empty(len(sums) + record_size(params))
                self.comm.broadcast_(record, (team.ranks if ours else team.other)[0])
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
        if normalizers[0].until is not None and normalizers[0].count >= normalizers[0].until:
            return  # frozen (``policy.obs_normalization_until``): both saw the same observations
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


def build_ppo(
    config: Config, env: MujocoVecEnv, info: RankInfo, phases: Phases | None = None, say: Callable[[str], None] = print
) -> FusedPPO:
    """``say``: where the collectives say a fallback to gloo (``ftrain.comm.collectives``)."""
    obs = env.get_observations()
    actor = build_actor(config, obs, env.num_actions)
    critic = build_model(config, obs, "critic", 1)
    storage = RolloutStorage("rl", env.num_envs, config.num_steps_per_env, obs, [env.num_actions])
    a = config.algorithm
    comm, team_traffic = _build_comm(config, env, info, [actor, critic], say)
    team = build_team(config, info, comm, team_traffic)
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
        comm=comm,
        shared_seed=run_seed(config.seed, "update"),
        reshuffle_each_epoch=a.reshuffle_each_epoch,
        phases=phases,
        team=team,
    )


def _build_comm(
    config: Config, env: MujocoVecEnv, info: RankInfo, models: list[nn.Module], say: Callable[[str], None]
) -> tuple[Comm, Traffic]:
    """The comm of all ranks, sized for what the update sends, and what a split update's team member sends its team."""
    sizes = [sum(p.numel() for p in model.parameters()) for model in models]
    samples = env.num_envs * config.num_steps_per_env
    small = max(SMALL_GATHERS, 2 * (env.num_obs + 1))  # (the observation normalizer's moments)
    if splits_update(config, info):  # the rollout gathered; each team's model with Adam's state broadcast
        rollout = samples * (env.num_obs + 3 * env.num_actions + 4)
        record = 3 + max(record_size(list(model.parameters())) for model in models)
        traffic = Traffic(per_rank=max(rollout, small), broadcast=record)
    else:  # both models' gradients, the KL and the losses; the advantages gathered
        traffic = Traffic(per_rank=max(sum(sizes) + 4, samples, small))
    comm = Comm.build(info, traffic, config.dist_timeout, config.shared_memory_all_reduce, say)
    return comm, Traffic(per_rank=max(sizes) + 4)


def build_algorithm(
    config: Config, env: MujocoVecEnv, info: RankInfo, phases: Phases, say: Callable[[str], None]
) -> tuple[PPO | Distillation, Comm]:
    """The algorithm and the comm the training loop's own collectives go through. ``phases``: where PPO's update
    charges its collectives (rsl-rl's Distillation keeps its own, over gloo, in its update)."""
    if config.algorithm.class_name == "Distillation":
        small = Traffic(per_rank=SMALL_GATHERS)
        return build_distillation(config, env, info), Comm.build(info, small, config.dist_timeout, False, say)
    alg = build_ppo(config, env, info, phases, say)
    return alg, alg.comm


def load_learned_state(alg: PPO | Distillation, state: dict, learning_rate: float) -> None:
    """Models (with normalizers) and optimizer from rsl-rl's keys in ``state``; the adaptive learning rate."""
    alg.load(state, load_cfg=None, strict=True)
    alg.learning_rate = learning_rate
    for group in alg.optimizer.param_groups:
        group["lr"] = learning_rate
