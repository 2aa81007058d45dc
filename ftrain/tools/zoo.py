"""stable-baselines3 PPO with the RL Zoo's tuned hyperparameters: the peer that ``ftrain bench`` and the learning
benchmark (``launch/bench_learning.py``) measure ftrain's shipped configs against.

The hyperparameters are those of rl-baselines3-zoo's ``hyperparams/ppo.yml`` for the v3 environments, run here on
v5: VecNormalize (observations and rewards, the algorithm's gamma), one environment. HalfCheetah and Hopper have
tuned entries with ReLU 256x256 networks and a low initial action noise; Walker2d's tuned entry keeps SB3's network
(64x64 tanh, orthogonal initialisation, std 1); Ant uses the Zoo's MuJoCo defaults, i.e. SB3's PPO defaults.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class ZooEntry:
    zoo_return: float
    """The Zoo's PPO after 1M steps (its benchmark.md; deterministic evaluation, v3 environments)."""
    ppo: dict = field(default_factory=dict)
    """Arguments of SB3's PPO besides the environment; ``relu_256`` below stands for the tuned networks."""
    relu_256: bool = False


ZOO = {
    "HalfCheetah-v5": ZooEntry(
        5819,
        dict(
            n_steps=512, batch_size=64, gamma=0.98, learning_rate=2.0633e-05, ent_coef=0.000401762, clip_range=0.1,
            n_epochs=20, gae_lambda=0.92, max_grad_norm=0.8, vf_coef=0.58096,
        ),
        relu_256=True,
    ),
    "Hopper-v5": ZooEntry(
        2410,
        dict(
            n_steps=512, batch_size=32, gamma=0.999, learning_rate=9.80828e-05, ent_coef=0.00229519, clip_range=0.2,
            n_epochs=5, gae_lambda=0.99, max_grad_norm=0.7, vf_coef=0.835671,
        ),
        relu_256=True,
    ),
    "Walker2d-v5": ZooEntry(
        3479,
        dict(
            n_steps=512, batch_size=32, gamma=0.99, learning_rate=5.05041e-05, ent_coef=0.000585045, clip_range=0.1,
            n_epochs=20, gae_lambda=0.95, max_grad_norm=1.0, vf_coef=0.871923,
        ),
    ),
    "Ant-v5": ZooEntry(1327),
}  # fmt: skip


def zoo_ppo(env_id: str, seed: int = 0, **kwargs):
    """SB3's PPO for ``env_id`` with the Zoo's hyperparameters, on one torch thread (its fastest on 2 cores: with
    two threads its small minibatches run several times slower)."""
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    torch.set_num_threads(1)
    entry = ZOO[env_id]
    arguments = dict(entry.ppo)
    if entry.relu_256:
        network = {"pi": [256, 256], "vf": [256, 256]}
        arguments["policy_kwargs"] = dict(
            log_std_init=-2, ortho_init=False, activation_fn=torch.nn.ReLU, net_arch=network
        )
    env = VecNormalize(make_vec_env(env_id, n_envs=1, seed=seed), gamma=arguments.get("gamma", 0.99))
    return PPO("MlpPolicy", env, device="cpu", seed=seed, **arguments, **kwargs)
