"""The gait of a trained planar runner (HalfCheetah, Hopper, Walker2d): per deterministic episode, its return, its
mean forward speed and how far its torso pitched. Tells a slow gait that stays upright from one that rears up or
turns over, where the return alone looks the same (docs/learning.md).

    .venv/bin/python launch/gait.py STORAGE [--episodes 10]

STORAGE is anything ``ftrain play`` takes (a run's storage, a checkpoint, a policy snapshot, an export). Episodes are
seeded from the config's evaluation seed, as the benchmark's final evaluation, but played one at a time where the
benchmark plays ten in a batch: the actions differ in their last bits, and a gait on the edge of turning over may
fall in other episodes. Speed is the mean of the root's forward velocity (``data.qvel[0]``, m/s), pitch the largest
``|data.qpos[2]|`` (the ``rooty`` hinge, rad) of each episode.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from ftrain.config import EnvConfig
from ftrain.errors import UserError
from ftrain.policy.options import check_play_options

if TYPE_CHECKING:
    from ftrain.policy.rollout import Act

PITCH_JOINT = "rooty"
"""The torso's pitch hinge, third joint of gymnasium's planar runners (after ``rootx`` and ``rootz``)."""


@dataclass(frozen=True)
class Gait:
    ret: float
    speed: float
    """Mean forward velocity of the root over the episode (m/s)."""
    pitch: float
    """Largest absolute torso pitch of the episode (rad): past 1.4 a runner rears up, near 3 it lies on its back."""


def gait(act: Act, env_config: EnvConfig, episodes: int, seed: int) -> list[Gait]:
    """``episodes`` deterministic episodes of ``act`` seeded ``seed``, ``seed + 1``, ...; UserError if the environment
    is not a planar runner."""
    from ftrain.policy.robot import make_env  # torch and MuJoCo: after the arguments are read
    from ftrain.policy.rollout import rollout

    env = make_env(env_config)
    try:
        data, model = env.unwrapped.data, env.unwrapped.model
        if model.njnt < 3 or model.joint(2).name != PITCH_JOINT:
            raise UserError(
                f"{env_config.id} is not a planar runner (its third joint is not {PITCH_JOINT!r}); gait.py "
                "measures HalfCheetah, Hopper and Walker2d"
            )
        speeds: list[float] = []
        pitches: list[float] = []
        gaits: list[Gait] = []

        def observe(_obs) -> None:
            speeds.append(float(data.qvel[0]))
            pitches.append(abs(float(data.qpos[2])))

        def finish(_number: int, episode) -> None:
            gaits.append(Gait(episode.ret, statistics.fmean(speeds), max(pitches)))
            speeds.clear()
            pitches.clear()

        rollout(env, act, episodes, seed, on_observation=observe, on_episode=finish)
        return gaits
    finally:
        env.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("storage", help="a run's storage, a checkpoint, a policy snapshot or an exported policy")
    parser.add_argument("--episodes", type=int, default=10)
    args = parser.parse_args()
    try:
        check_play_options(args.episodes, 0, None)
        from ftrain.policy.load import load_policy

        policy = load_policy(args.storage)
        gaits = gait(policy.act, policy.config.env, args.episodes, policy.config.eval.seed)
    except UserError as error:
        sys.exit(f"gait.py: {error}")
    for number, episode in enumerate(gaits, 1):
        print(
            f"episode {number}: return {episode.ret:,.0f}, mean speed {episode.speed:.2f} m/s, "
            f"largest |pitch| {episode.pitch:.2f} rad"
        )


if __name__ == "__main__":
    main()
