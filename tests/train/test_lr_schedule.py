"""The linear learning-rate schedule: a function of the iteration alone, zero from its horizon on."""

from types import SimpleNamespace

import pytest
import torch

from ftrain.config import AlgorithmConfig
from ftrain.train.lr_schedule import build_lr_schedule, horizon_notice


def test_linear_schedule_falls_to_zero_at_its_horizon() -> None:
    assert build_lr_schedule(AlgorithmConfig(schedule="adaptive")) is None
    schedule = build_lr_schedule(AlgorithmConfig(learning_rate=1e-3, schedule="linear", schedule_iterations=4))
    alg = SimpleNamespace(learning_rate=1e-3, optimizer=torch.optim.Adam([torch.zeros(1, requires_grad=True)]))
    rates = []
    for iteration in (0, 1, 2, 3, 4, 5, 1):
        schedule.apply(alg, iteration)
        assert alg.optimizer.param_groups[0]["lr"] == alg.learning_rate
        rates.append(alg.learning_rate)
    assert rates == pytest.approx([1e-3, 7.5e-4, 5e-4, 2.5e-4, 0.0, 0.0, 7.5e-4])


def test_a_horizon_other_than_the_runs_length_is_said_with_the_rate_it_ends_at() -> None:
    linear = AlgorithmConfig(learning_rate=1e-3, schedule="linear", schedule_iterations=1954)
    assert horizon_notice(linear, 1954) is None
    assert horizon_notice(AlgorithmConfig(schedule="adaptive", schedule_iterations=1954), 200) is None
    short = horizon_notice(linear, 200)
    assert "ends at 0.000898" in short and "algorithm.schedule_iterations=200" in short, short
    assert "the last 46 iterations run at rate 0" in horizon_notice(linear, 2000)
