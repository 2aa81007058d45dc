"""What a refused resume names: the keys that keep two models from loading into each other, and only those."""

from __future__ import annotations

from ftrain.ckpt.changes import model_change
from ftrain.config import load_config

from helpers import SMOKE


def test_a_model_change_names_each_key_that_decides_the_tensors_and_none_other() -> None:
    saved = load_config(SMOKE).public_dict()
    assert model_change(saved, saved) is None
    free = load_config(
        SMOKE,
        [
            "policy.obs_normalization_until=1000",
            "policy.final_noise_std=0.2",
            "algorithm.schedule=linear",
            "algorithm.schedule_iterations=8",
        ],
    ).public_dict()
    assert model_change(saved, free) is None, "when the normalizers freeze and where the noise ends: no new tensors"
    other = load_config(SMOKE, ["env.id=Hopper-v5", "policy.hidden_dims=[32,32]", "algorithm.gamma=0.9"]).public_dict()
    assert (
        model_change(saved, other) == 'env.id "HalfCheetah-v5" -> "Hopper-v5"; policy.hidden_dims [16, 16] -> [32, 32]'
    )
