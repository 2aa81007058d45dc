"""Run under torchrun at two ranks: one rollout and one split update (rank 0 learns the actor, rank 1 the critic).
Rank 0 saves, to OUT, what the update started from (models, optimizer, the gathered batch, and the state of the shared
generator its sample orders come from) and what it ended with; every rank saves its end state to OUT.RANK, so the
test can replay the update on one rank."""

from __future__ import annotations

import copy
import sys

from ftrain.process import exit_fast, imports

with imports():  # as ftrain's own workers import: a cold start at half the CPU
    import torch
    from equivalence_worker import rollout

    from ftrain.comm import group
    from ftrain.config import load_config
    from ftrain.train.envs import MujocoVecEnv
    from ftrain.train.ppo import build_ppo


def main(out: str, *overrides: str) -> None:
    info = group.init(30)
    torch.set_num_threads(1)
    config = load_config("configs/smoke.yaml", list(overrides))
    group.seed_all(config.seed)
    first_env = info.rank * config.env.num_envs
    env = MujocoVecEnv(config.env.id, config.env.num_envs, group.env_seed(config.seed, first_env), config.env.kwargs)
    alg = build_ppo(config, env, info)
    assert alg.team is not None, "an even number of ranks splits the update by default"
    rollout(alg, env, config.num_steps_per_env)
    start = {"models": copy.deepcopy(alg.save()), "learning_rate": alg.learning_rate}
    start["shared_rng"] = alg.shared_generator.get_state()  # the update's sample orders are drawn from it
    batch = alg._gathered_rollout()
    alg._gathered_rollout = lambda: batch
    start |= {"fields": batch.fields, "advantages": batch.advantages}
    losses = alg.update()
    end = {"models": alg.save(), "losses": losses, "learning_rate": alg.learning_rate}
    if info.is_main:
        torch.save({"start": start, "end": end}, out)
    torch.save(end, f"{out}.{info.rank}")
    group.shutdown()


if __name__ == "__main__":
    main(*sys.argv[1:])
    exit_fast(0)  # without the interpreter's teardown of torch, as ftrain's workers end
