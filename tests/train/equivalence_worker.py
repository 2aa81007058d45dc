"""Run alone: FusedPPO and rsl-rl's own PPO, from the same weights, the same environment state and the same random
streams (FusedPPO's shared generator in the state of torch's, which rsl-rl draws from), must produce the same actions
and, after an update, the same learned state. (At N ranks, FusedPPO trains what it trains here on all the
environments: tests/train/test_world_size.py.)"""

from __future__ import annotations

import copy
import json
import sys

from ftrain.process import exit_fast, imports

with imports():  # as ftrain's own workers import: a cold start at half the CPU
    import torch
    from rsl_rl.algorithms import PPO
    from rsl_rl.storage import RolloutStorage

    from ftrain.comm import group
    from ftrain.config import load_config
    from ftrain.train.envs import MujocoVecEnv
    from ftrain.train.ppo import build_ppo


def rollout(alg, env: MujocoVecEnv, steps: int) -> list[torch.Tensor]:
    """``steps`` environment steps into ``alg``'s storage, then the returns; the actions taken."""
    alg.train_mode()
    actions = []
    obs = env.get_observations()
    with torch.inference_mode():
        for _ in range(steps):
            action = alg.act(obs)
            actions.append(action.clone())
            obs, rewards, dones, extras = env.step(action)
            alg.process_env_step(obs, rewards, dones, extras)
        alg.compute_returns(obs)
    return actions


def rollout_and_update(alg, env: MujocoVecEnv, steps: int) -> tuple[list[torch.Tensor], dict]:
    return rollout(alg, env, steps), alg.update()


def main(out: str) -> None:
    info = group.init(30)
    torch.set_num_threads(1)
    config = load_config("configs/smoke.yaml", ["env.num_envs=8", "algorithm.num_mini_batches=4", "split_update=false"])
    seed = group.rank_seed(config.seed, info.rank)
    group.seed_all(config.seed)
    env = MujocoVecEnv(config.env.id, config.env.num_envs, seed, config.env.kwargs)
    ours = build_ppo(config, env, info)
    # rsl-rl's PPO with copies of the same models, and its own optimizer, storage and synchronisation
    storage = RolloutStorage("rl", env.num_envs, config.num_steps_per_env, env.get_observations(), [env.num_actions])
    a = config.algorithm
    theirs = PPO(
        copy.deepcopy(ours._raw_actor),
        copy.deepcopy(ours._raw_critic),
        storage,
        num_learning_epochs=a.num_learning_epochs,
        num_mini_batches=a.num_mini_batches,
        learning_rate=a.learning_rate,
        entropy_coef=a.entropy_coef,
        multi_gpu_cfg=info.rsl_rl_cfg(),
    )
    start_env, start_rng = env.get_state(), group.rng_state()
    results = {}
    for name, alg in (("ours", ours), ("theirs", theirs)):
        env.set_state(start_env)
        group.set_rng_state(start_rng)
        ours.shared_generator.set_state(start_rng["torch"])
        actions, losses = rollout_and_update(alg, env, config.num_steps_per_env)
        results[name] = (actions, losses, alg)
    (a_ours, l_ours, ours), (a_theirs, l_theirs, theirs) = results["ours"], results["theirs"]
    report = {
        "actions_equal": all(torch.equal(x, y) for x, y in zip(a_ours, a_theirs, strict=True)),
        "learning_rates": [ours.learning_rate, theirs.learning_rate],
        "losses": [l_ours, {k: l_theirs[k] for k in l_ours}],
        "max_param_diff": max(
            (p - q).abs().max().item()
            for m1, m2 in ((ours.actor, theirs.actor), (ours.critic, theirs.critic))
            for p, q in zip(m1.state_dict().values(), m2.state_dict().values(), strict=True)
            if p.is_floating_point()
        ),
    }
    if info.is_main:
        with open(out, "w") as file:
            json.dump(report, file)
    group.shutdown()


if __name__ == "__main__":
    main(sys.argv[1])
    exit_fast(0)  # without the interpreter's teardown of torch, as ftrain's workers end
