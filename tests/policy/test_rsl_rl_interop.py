"""Checkpoints in the standard format: rsl-rl's own OnPolicyRunner.load() opens ftrain's common.pt, and its
inference policy acts exactly like ftrain's policy of the same step."""

from __future__ import annotations

import contextlib
import io

import pytest
import torch
from rsl_rl.runners import OnPolicyRunner
from tensordict import TensorDict

from ftrain.ckpt.format import COMMON, learned_state, state_digest
from ftrain.policy.export import sample_observations
from ftrain.policy.load import load_policy
from ftrain.policy.model import OBS_GROUP, rsl_rl_runner_cfg
from ftrain.train.envs import MujocoVecEnv

from helpers import final_manifest, run_train


@pytest.mark.slow  # trains first
@pytest.mark.parametrize("ranks", [1, 2])
def test_rsl_rl_loads_the_newest_common_pt_and_acts_like_ftrain(tmp_path, ranks: int) -> None:
    storage = tmp_path / "run"
    run_train(storage, "iterations=4", ranks=ranks, supervised=ranks > 1)
    manifest = final_manifest(storage)
    path = storage / "checkpoints" / f"step-{manifest['step']:09d}" / COMMON
    plain = torch.load(path, weights_only=True)
    assert {"actor_state_dict", "critic_state_dict", "optimizer_state_dict", "iter", "infos"} <= plain.keys()
    assert plain["iter"] == 4
    assert state_digest(learned_state(plain)) == manifest["state_sha256"]

    policy = load_policy(str(storage))
    env = MujocoVecEnv(policy.config.env.id, 1, 0, policy.config.env.kwargs)
    with contextlib.redirect_stdout(io.StringIO()):
        runner = OnPolicyRunner(env, rsl_rl_runner_cfg(policy.config), log_dir=None, device="cpu")
    runner.load(str(path))
    assert runner.current_learning_iteration == 4
    theirs = runner.get_inference_policy()
    obs = sample_observations(policy)
    with torch.inference_mode():
        expected = theirs(TensorDict({OBS_GROUP: obs}, batch_size=[len(obs)]))
    assert torch.equal(policy.act(obs), expected)
    env.close()
