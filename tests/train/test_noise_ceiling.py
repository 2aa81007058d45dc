"""``policy.final_noise_std``: the action noise's ceiling falls linearly to it over the learning rate's horizon, and
the learned noise rules where it is lower."""

from __future__ import annotations

import pytest

from ftrain.policy.load import load_policy
from ftrain.policy.model import action_std

from helpers import metrics_by_iteration, run_train

pytestmark = pytest.mark.slow

LINEAR_LOG_STD = ["iterations=5", "algorithm.schedule=linear", "algorithm.schedule_iterations=4", "policy.std_type=log"]


def _action_std(tmp_path, name: str, *overrides: str) -> list[float]:
    storage = tmp_path / name
    run_train(storage, *LINEAR_LOG_STD, f"log_dir={tmp_path / name / 'logs'}", *overrides)
    rows = metrics_by_iteration(tmp_path / name / "logs")
    return [float(rows[iteration]["action_std"]) for iteration in sorted(rows)]


def test_the_noise_follows_its_ceiling_down_to_the_final_noise_and_stays(tmp_path) -> None:
    free = _action_std(tmp_path, "free", "policy.init_noise_std=1.0")
    capped = _action_std(tmp_path, "capped", "policy.init_noise_std=1.0", "policy.final_noise_std=0.2")
    assert all(0.95 < std < 1.05 for std in free), free  # the learned noise barely moves in 5 iterations
    # the update of iteration i (from 1) trains under the ceiling of i - 1 completed: 1.0, 0.8, 0.6, 0.4, then 0.2 on
    assert capped[0] <= 1.0 + 1e-6, capped
    assert capped[1:] == pytest.approx([0.8, 0.6, 0.4, 0.2], abs=1e-6), capped
    # a policy loaded from the run (ftrain play --stochastic) samples with the noise of its step, not the learned one
    assert action_std(load_policy(str(tmp_path / "capped")).actor) == pytest.approx(0.2, abs=1e-6)
    assert action_std(load_policy(str(tmp_path / "free")).actor) == pytest.approx(free[-1], abs=1e-6)
