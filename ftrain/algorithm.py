"""rsl-rl's PPO built from an ftrain config, with its data-parallel update using one collective per minibatch.

rsl-rl's own multi-process update issues three collectives per minibatch (gradient all-reduce, KL all-reduce,
learning-rate broadcast). :class:`FusedPPO` packs the KL into the gradient buffer and lets every rank apply the
same adaptive learning-rate rule to the same global KL, which is what rank 0 would have broadcast: the update is
mathematically the same synchronous data-parallel PPO with a third of the round trips.
"""

from __future__ import annotations

import hashlib

import torch
import torch.distributed as dist
from rsl_rl.algorithms import PPO
from rsl_rl.models import MLPModel
from rsl_rl.storage import RolloutStorage
from torch import nn

from ftrain.config import Config
from ftrain.distributed import RankInfo
from ftrain.envs import OBS_GROUP, MujocoVecEnv

OBS_GROUPS = {"actor": [OBS_GROUP], "critic": [OBS_GROUP]}


class FusedPPO(PPO):
    """rsl-rl PPO (MLP policies) whose update averages gradients and KL in a single all-reduce per minibatch."""

    def update(self) -> dict[str, float]:
        sums = {"value": 0.0, "surrogate": 0.0, "entropy": 0.0}
        params = [p for group in self.optimizer.param_groups for p in group["params"]]
        for batch in self.storage.mini_batch_generator(self.num_mini_batches, self.num_learning_epochs):
            if self.normalize_advantage_per_mini_batch:
                with torch.no_grad():
                    batch.advantages = (batch.advantages - batch.advantages.mean()) / (batch.advantages.std() + 1e-8)
            self.actor(batch.observations, stochastic_output=True)
            actions_log_prob = self.actor.get_output_log_prob(batch.actions)
            values = self.critic(batch.observations)
            entropy = self.actor.output_entropy
            adaptive = self.desired_kl is not None and self.schedule == "adaptive"
            if adaptive:
                with torch.inference_mode():
                    kl = self.actor.get_kl_divergence(
                        batch.old_distribution_params, self.actor.output_distribution_params
                    )
                    kl_mean = torch.mean(kl)

            ratio = torch.exp(actions_log_prob - torch.squeeze(batch.old_actions_log_prob))
            advantages = torch.squeeze(batch.advantages)
            surrogate = -advantages * ratio
            surrogate_clipped = -advantages * torch.clamp(ratio, 1.0 - self.clip_param, 1.0 + self.clip_param)
            surrogate_loss = torch.max(surrogate, surrogate_clipped).mean()
            if self.use_clipped_value_loss:
                value_clipped = batch.values + (values - batch.values).clamp(-self.clip_param, self.clip_param)
                value_loss = torch.max((values - batch.returns).pow(2), (value_clipped - batch.returns).pow(2)).mean()
            else:
                value_loss = (batch.returns - values).pow(2).mean()
            loss = surrogate_loss + self.value_loss_coef * value_loss - self.entropy_coef * entropy.mean()

            self.optimizer.zero_grad()
            loss.backward()
            if self.is_multi_gpu:
                kl_mean = self._all_reduce_mean(params, kl_mean if adaptive else None)
            if adaptive:
                self._adapt_learning_rate(kl_mean)
            nn.utils.clip_grad_norm_(self.actor.parameters(), self.max_grad_norm)
            nn.utils.clip_grad_norm_(self.critic.parameters(), self.max_grad_norm)
            self.optimizer.step()

            sums["value"] += value_loss.item()
            sums["surrogate"] += surrogate_loss.item()
            sums["entropy"] += entropy.mean().item()

        obs = self.storage.observations.flatten(0, 1)
        self.actor.update_normalization(obs)
        self.critic.update_normalization(obs)
        self.storage.clear()
        num_updates = self.num_learning_epochs * self.num_mini_batches
        return {key: value / num_updates for key, value in sums.items()}

    def _all_reduce_mean(self, params: list[nn.Parameter], kl_mean: torch.Tensor | None) -> torch.Tensor | None:
        """Average every gradient (and the KL, riding in the same buffer) over all ranks, in place."""
        grads = [p.grad.view(-1) for p in params if p.grad is not None]
        extra = [kl_mean.view(1).to(grads[0].dtype)] if kl_mean is not None else []
        packed = torch.cat(grads + extra)
        dist.all_reduce(packed)
        packed /= self.gpu_world_size
        offset = 0
        for grad in grads:
            grad.copy_(packed[offset : offset + grad.numel()])
            offset += grad.numel()
        return packed[offset] if kl_mean is not None else None

    def _adapt_learning_rate(self, kl_mean: torch.Tensor) -> None:
        """rsl-rl's adaptive schedule; every rank computes it from the same global KL, so no broadcast is needed."""
        if kl_mean > self.desired_kl * 2.0:
            self.learning_rate = max(1e-5, self.learning_rate / 1.5)
        elif kl_mean < self.desired_kl / 2.0 and kl_mean > 0.0:
            self.learning_rate = min(1e-2, self.learning_rate * 1.5)
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate


def policy_kwargs(config: Config) -> dict:
    """Constructor arguments of rsl-rl's MLPModel for the actor (the critic uses the same, deterministic)."""
    return {
        "hidden_dims": list(config.policy.hidden_dims),
        "activation": config.policy.activation,
        "obs_normalization": config.policy.obs_normalization,
    }


def build_actor(config: Config, obs, num_actions: int, obs_set: str = "actor") -> MLPModel:
    distribution = {"class_name": "GaussianDistribution", "init_std": config.policy.init_noise_std}
    return MLPModel(
        obs, {obs_set: [OBS_GROUP]}, obs_set, num_actions, **policy_kwargs(config), distribution_cfg=distribution
    )


def build_ppo(config: Config, env: MujocoVecEnv, info: RankInfo) -> FusedPPO:
    obs = env.get_observations()
    actor = build_actor(config, obs, env.num_actions)
    critic = MLPModel(obs, OBS_GROUPS, "critic", 1, **policy_kwargs(config))
    storage = RolloutStorage("rl", env.num_envs, config.num_steps_per_env, obs, [env.num_actions])
    a = config.algorithm
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
    )


def learned_state(alg: PPO) -> dict:
    """What training has learned: models (with normalizers), optimizer, adaptive learning rate."""
    return {**alg.save(), "learning_rate": alg.learning_rate}


def load_learned_state(alg: PPO, state: dict) -> None:
    alg.load(state, load_cfg=None, strict=True)
    alg.learning_rate = state["learning_rate"]
    for group in alg.optimizer.param_groups:
        group["lr"] = alg.learning_rate


def state_digest(state: object) -> str:
    """SHA-256 over every tensor and number in ``state``, in a canonical order: equal iff bitwise equal."""
    digest = hashlib.sha256()
    _feed(digest, state)
    return digest.hexdigest()


def _feed(digest: hashlib._Hash, value: object) -> None:
    if isinstance(value, torch.Tensor):
        tensor = value.detach().contiguous().cpu()
        digest.update(f"T{tensor.dtype}{tuple(tensor.shape)}".encode())
        digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
    elif isinstance(value, dict):
        digest.update(b"D")
        for key in sorted(value, key=str):
            digest.update(repr(key).encode())
            _feed(digest, value[key])
    elif isinstance(value, (list, tuple)):
        digest.update(b"L")
        for item in value:
            _feed(digest, item)
    else:
        digest.update(repr(value).encode())
