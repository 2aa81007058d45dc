"""The policy network of a config: rsl-rl's MLP actor, built the same way for training, loading and export; its action
standard deviation read from the parameter."""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel
from rsl_rl.modules import EmpiricalNormalization
from rsl_rl.modules.distribution import GaussianDistribution
from tensordict import TensorDict

from ftrain.config import Config

OBS_GROUP = "policy"
"""The one observation group of ftrain's environments, as rsl-rl's models read it."""


class ClippedNormalization(EmpiricalNormalization):
    """rsl-rl's observation normalizer with its output clipped to ±``clip``, as SB3's VecNormalize clips (at 10).

    Why: a feature that is nearly always the same (Ant's contact forces) has a tiny running std, and its rare spikes
    would reach the network as values in the hundreds. Same buffers as rsl-rl's, so the state dicts are the same;
    exports (TorchScript, ONNX) copy this module and clip as well.
    """

    def __init__(self, shape: int, clip: float) -> None:
        super().__init__(shape)
        self.clip = clip

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self._mean) / (self._std + self.eps)).clamp(-self.clip, self.clip)


def policy_kwargs(config: Config) -> dict:
    """Constructor arguments of rsl-rl's MLPModel for the actor and the critic (ftrain's clipping aside)."""
    return {
        "hidden_dims": list(config.policy.hidden_dims),
        "activation": config.policy.activation,
        "obs_normalization": config.policy.obs_normalization,
    }


def build_model(config: Config, obs, obs_set: str, output_dim: int, distribution: dict | None = None) -> MLPModel:
    """An rsl-rl MLPModel with the config's network and observation normalisation (clipped if ``policy.obs_clip``)."""
    model = MLPModel(
        obs, {obs_set: [OBS_GROUP]}, obs_set, output_dim, **policy_kwargs(config), distribution_cfg=distribution
    )
    if config.policy.obs_normalization and config.policy.obs_clip > 0:
        model.obs_normalizer = ClippedNormalization(model.obs_dim, config.policy.obs_clip)
    if config.policy.obs_normalization and config.policy.obs_normalization_until:
        model.obs_normalizer.until = config.policy.obs_normalization_until
    return model


def distribution_cfg(config: Config) -> dict:
    """rsl-rl's config of the actor's action distribution."""
    return {
        "class_name": "GaussianDistribution",
        "init_std": config.policy.init_noise_std,
        "std_type": config.policy.std_type,
    }


def build_actor(config: Config, obs, num_actions: int, obs_set: str = "actor") -> MLPModel:
    return build_model(config, obs, obs_set, num_actions, distribution_cfg(config))


def rsl_rl_runner_cfg(config: Config) -> dict:
    """The ``train_cfg`` with which rsl-rl's ``OnPolicyRunner`` builds the models of ``config`` as ftrain does, so that
    its ``load()`` opens ftrain's ``common.pt`` (PPO runs) unchanged."""
    model = {"class_name": "MLPModel", **policy_kwargs(config)}
    return {
        "num_steps_per_env": config.num_steps_per_env,
        "save_interval": config.checkpoint.interval,
        "obs_groups": {"actor": [OBS_GROUP], "critic": [OBS_GROUP]},
        "actor": {**model, "distribution_cfg": distribution_cfg(config)},
        "critic": model,
        "algorithm": {"class_name": "PPO", "learning_rate": config.algorithm.learning_rate},
    }


def actor_actions(actor: MLPModel, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
    """The rsl-rl actor's actions for a batch of observations: the mean, or a sample (global torch RNG)."""
    with torch.inference_mode():
        return actor(TensorDict({OBS_GROUP: obs}, batch_size=[obs.shape[0]]), stochastic_output=not deterministic)


def action_std(policy: MLPModel) -> float:
    """The mean standard deviation of ``policy``'s actions as it is now: from the parameter of rsl-rl's Gaussian
    distribution (the update no longer passes its batches through the distribution), else the last batch's."""
    distribution = policy.distribution
    if type(distribution) is GaussianDistribution:
        return gaussian_std(distribution).mean().item()
    return policy.output_std.mean().item()


def gaussian_std(distribution: GaussianDistribution) -> torch.Tensor:
    """The standard deviation rsl-rl's distribution samples with, per action dimension, from its parameter as it is now
    (``distribution.std`` is the one of the last batch the distribution saw)."""
    if distribution.std_type == "log":
        return gaussian_log_std(distribution).exp()
    return distribution.std_param.clamp(*distribution.std_range)


def gaussian_log_std(distribution: GaussianDistribution) -> torch.Tensor:
    """The log of the standard deviation rsl-rl's distribution samples with (clamped to its range), in either of its
    parameterisations; differentiable with respect to the parameter."""
    if distribution.std_type == "log":
        return distribution.log_std_param.clamp(*distribution.log_std_range)
    return distribution.std_param.clamp(*distribution.std_range).log()
