"""The gait of a policy in a real MuJoCo runner: speed and pitch per episode, and a clear refusal off planar runners."""

import math

import pytest
import torch
from gait import gait

from ftrain.config import EnvConfig
from ftrain.errors import UserError

STEPS = 300
CHEETAH = EnvConfig("HalfCheetah-v5", kwargs={"max_episode_steps": STEPS})


class Wave:
    """An open-loop policy: each actuator a sine of its own phase. It throws the cheetah onto its back."""

    def __init__(self) -> None:
        self.step, self.control_cost = 0, 0.0

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        self.step += 1
        action = torch.tensor([[math.sin(0.4 * self.step + joint) for joint in range(6)]])
        self.control_cost += 0.1 * float(action.square().sum())  # HalfCheetah-v5's ctrl_cost_weight
        return action


def test_a_cheetah_thrown_on_its_back_shows_its_pitch_and_its_speed_matches_its_return() -> None:
    still = gait(lambda obs: torch.zeros(obs.shape[0], 6), CHEETAH, episodes=2, seed=7)
    assert len(still) == 2
    for episode in still:
        assert abs(episode.speed) < 0.05 and episode.pitch < 0.3  # it settles where it was dropped
    wave = Wave()
    thrown = gait(wave, CHEETAH, episodes=1, seed=7)[0]
    assert thrown.pitch > 2.5  # on its back (pi rad), where a return near zero looks like standing still
    progress = thrown.ret + wave.control_cost  # the forward reward: the distance run over the time step, summed
    assert progress == pytest.approx(thrown.speed * STEPS, abs=2.0)


def test_a_runner_without_a_pitch_hinge_is_refused_by_name() -> None:
    with pytest.raises(UserError, match="Ant-v5 is not a planar runner"):
        gait(lambda obs: torch.zeros(obs.shape[0], 8), EnvConfig("Ant-v5"), episodes=1, seed=0)
