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


def distribution_cfg(config: Config) -> dict:
    """rsl-rl's config of the actor's action distribution."""
    return {
        "class_name": "GaussianDistribution",
        "init_std": config.policy.init_noise_std,
        "std_type": config.policy.std_type,
    }


def build_actor(config: Config, obs, num_actions: int, obs_set: str = "actor") -> MLPModel:
    return MLPModel(
        obs,
        {obs_set: [OBS_GROUP]},
        obs_set,
        num_actions,
        **policy_kwargs(config),
        distribution_cfg=distribution_cfg(config),
    )


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
