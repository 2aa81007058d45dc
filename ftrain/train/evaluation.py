"""Policy rollouts in an environment of their own, and the evaluation hook that scores training with them.

Evaluation never touches what training continues from: it steps a separate environment seeded on its own, takes the
actor's deterministic (mean) actions, so no random number is drawn, and only reads the observation normalizer.
Training with and without evaluation therefore learns bit for bit the same.
"""

from __future__ import annotations

import math
import time

import gymnasium as gym

from ftrain.comm import group
from ftrain.config import EvalConfig
from ftrain.heartbeat import Phase
from ftrain.policy.model import actor_actions
from ftrain.policy.robot import make_env
from ftrain.policy.rollout import rollout
from ftrain.train.hooks import Hook, TrainerView


class EvalHook(Hook):
    """Every ``eval.every`` iterations and at the run's last: ``eval.episodes`` deterministic episodes with fixed
    seeds, shared by the ranks (a block of consecutive episodes each, all at once in as many environments, one batched
    forward pass per step, each episode in its own row of a batch of all: ``rollout``'s ``rows``), so evaluating takes
    both cores instead of leaving one rank waiting for rank 0, and scores alike at any world size and as ``play``.

    Their mean return becomes ``metrics["eval_return"]``, which the logging hooks after this one write and the
    checkpoint manifest stores (so keep-best retention can rank by it), and the seconds the evaluation took
    ``metrics["eval_time"]`` (it is not part of ``iteration_time``). On the iterations in between both are NaN:
    present from the first iteration on (the CSV header is written then) but never a stale score that keep-best
    could mistake for a measurement of that step.
    """

    def __init__(self, config: EvalConfig) -> None:
        self.config = config
        self.envs: list[gym.Env] = []

    def after_iteration(self, trainer: TrainerView, metrics: dict[str, float]) -> None:
        if trainer.iteration % self.config.every and trainer.iteration != trainer.config.iterations:
            metrics["eval_return"] = metrics["eval_time"] = math.nan
            return
        trainer.heartbeat.beat(Phase.EVALUATE, trainer.iteration)  # a phase of its own for the supervisor's timing
        started = time.perf_counter()
        first, count = episode_share(self.config.episodes, trainer.info)
        if len(self.envs) < count:
            self.envs = [make_env(trainer.config.env) for _ in range(count)]
        episodes = []
        if count:
            actor = trainer.alg.get_policy()
            act = lambda obs: actor_actions(actor, obs)  # noqa: E731
            at = (first, self.config.episodes)  # each episode's row of all: the same returns at any world size
            episodes = rollout(self.envs, act, count, self.config.seed + first, rows=at)
        (total,) = trainer.comm.sum_values([sum(episode.ret for episode in episodes)])
        metrics["eval_return"] = total / self.config.episodes
        metrics["eval_time"] = time.perf_counter() - started

    def on_end(self, trainer: TrainerView) -> None:
        for env in self.envs:
            env.close()


def episode_share(episodes: int, info: group.RankInfo) -> tuple[int, int]:
    """The first episode and the number of episodes this rank evaluates: consecutive blocks, in rank order."""
    base, extra = divmod(episodes, info.world_size)
    return info.rank * base + min(info.rank, extra), base + (info.rank < extra)
