"""The policy network of a config: rsl-rl's MLP actor, built the same way for training, loading and export."""

from __future__ import annotations

import torch
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from ftrain.config import Config

OBS_GROUP = "policy"
"""The one observation group of ftrain's environments, as rsl-rl's models read it."""


def policy_kwargs(config: Config) -> dict:
    """Constructor arguments of rsl-rl's MLPModel for the actor (the critic uses the same, deterministic)."""
    return {
        "hidden_dims": list(config.policy.hidden_dims),
        "activation": config.policy.activation,
        "obs_normalization": config.policy.obs_normalization,
    }


def build_actor(config: Config, obs, num_actions: int, obs_set: str = "actor") -> MLPModel:
    distribution = {
        "class_name": "GaussianDistribution",
        "init_std": config.policy.init_noise_std,
        "std_type": config.policy.std_type,
    }
    return MLPModel(
        obs, {obs_set: [OBS_GROUP]}, obs_set, num_actions, **policy_kwargs(config), distribution_cfg=distribution
    )


def actor_actions(actor: MLPModel, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
    """The rsl-rl actor's actions for a batch of observations: the mean, or a sample (global torch RNG)."""
    with torch.inference_mode():
        return actor(TensorDict({OBS_GROUP: obs}, batch_size=[obs.shape[0]]), stochastic_output=not deterministic)
