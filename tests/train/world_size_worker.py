"""Run under torchrun at W ranks (or alone, W = 1): each case of CASES (a JSON file) whose ``worlds`` hold W trains
its iterations from a fresh start, through the real training loop (``Trainer``: rollout, reward normalisation, update,
metrics) without checkpoints, with its ``total_envs`` shared by the W ranks (none: the config's own count, as users
run it). Rank 0 saves
what each case learned, with the collectives' fallbacks, to ``OUT/<case>.w<W>.pt``."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from ftrain.process import exit_fast, imports

with imports():  # as ftrain's own workers import: a cold start at half the CPU
    import torch

    from ftrain.comm import group
    from ftrain.config import load_config
    from ftrain.policy.model import action_std
    from ftrain.train.trainer import Trainer

QUIET = ["log.console=false", "log.csv=false", "log.tensorboard=false", "eval.every=0", "snapshots.every=0"]


def main(cases_file: str, out: str) -> None:
    info = group.init(60)
    cases = json.loads(Path(cases_file).read_text())
    for name, case in cases.items():
        if info.world_size not in case["worlds"]:
            continue
        overrides = [*case["overrides"], *QUIET, f"iterations={case['iterations']}"]
        if "total_envs" in case:
            overrides.append(f"env.total_envs={case['total_envs']}")
        storage = f"{out}/storage-{name}-w{info.world_size}"
        config = load_config(case["config"], overrides, storage=storage)
        trainer = Trainer(config, info)
        trainer.alg.train_mode()
        for _ in range(case["iterations"]):
            trainer._iterate()
        if info.is_main:
            learned = {
                "models": trainer.alg.save(),
                "learning_rate": trainer.alg.learning_rate,
                "reward_norm": trainer.reward_norm.common_state() if trainer.reward_norm else None,
                "env_steps": trainer.env_steps,
                "fallbacks": trainer.comm.fallbacks,
                "update": trainer.run_description["update"]["kind"],
                "observations_normalized": [
                    int(model.obs_normalizer.count) for model in (trainer.alg.actor, trainer.alg.critic)
                ],
                "noise": action_std(trainer.alg.actor),
                "noise_ceiling": trainer.alg.actor.distribution.std_range[1],
            }
            torch.save(learned, f"{out}/{name}.w{info.world_size}.pt")
        trainer.checkpointer.shutdown()
        trainer.env.close()
    group.shutdown()


if __name__ == "__main__":
    main(*sys.argv[1:])
    exit_fast(0)  # without the interpreter's teardown of torch, as ftrain's workers end
