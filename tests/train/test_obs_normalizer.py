"""``policy.obs_normalization_until``: the observation normalizers stop learning once they have seen that many
observations, all ranks together, so that N ranks freeze them where one rank does, with the same statistics."""

from __future__ import annotations

import pytest
import torch

from helpers import final_manifest, run_train

pytestmark = pytest.mark.slow

BATCH = 8 * 16
"""Observations per iteration: env.total_envs=8 x configs/smoke.yaml's 16 steps."""


def _normalizers(storage) -> dict[str, dict[str, torch.Tensor]]:
    step = final_manifest(storage)["step"]
    common = torch.load(storage / "checkpoints" / f"step-{step:09d}" / "common.pt", weights_only=True)
    return {
        model: {key.removeprefix("obs_normalizer."): value for key, value in state.items() if "obs_normalizer" in key}
        for model, state in ((m, common[f"{m}_state_dict"]) for m in ("actor", "critic"))
    }


def test_the_normalizers_freeze_after_the_observations_asked_at_any_world_size(tmp_path) -> None:
    learned = {}
    for ranks, until in ((1, BATCH + 1), (2, BATCH + 1), (1, 0)):
        storage = tmp_path / f"ranks{ranks}-until{until}"
        overrides = ["iterations=3", "env.total_envs=8", f"policy.obs_normalization_until={until}"]
        run_train(storage, *overrides, ranks=ranks)
        learned[ranks, until] = _normalizers(storage)
    for model in ("actor", "critic"):
        one, two, never = (learned[key][model] for key in ((1, BATCH + 1), (2, BATCH + 1), (1, 0)))
        assert one["count"] == two["count"] == 2 * BATCH, model  # the update that passed BATCH + 1 was the last
        assert never["count"] == 3 * BATCH, model
        for key in ("_mean", "_var"):
            torch.testing.assert_close(two[key], one[key], rtol=1e-5, atol=1e-6)
            assert not torch.equal(never[key], one[key]), f"{model} {key}: the third update changed nothing"
