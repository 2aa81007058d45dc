"""FusedPPO is rsl-rl's PPO: the same actions and update on one rank; a split update of real ranks is one rank's update
of the gathered batch; a data-parallel rank learns from exactly the samples of the global batch that it holds."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import torch
from equivalence_worker import rollout

from ftrain.comm.group import RankInfo
from ftrain.config import load_config
from ftrain.train.envs import MujocoVecEnv
from ftrain.train.minibatch import Rollout, mini_batches
from ftrain.train.ppo import build_ppo, load_learned_state

from helpers import REPO, SMOKE, child_env


@pytest.mark.slow  # a worker process of its own
def test_fused_ppo_matches_rsl_rl_ppo(tmp_path) -> None:
    out = tmp_path / "report.json"
    subprocess.run(
        [sys.executable, str(REPO / "tests" / "train" / "equivalence_worker.py"), str(out)],
        cwd=REPO,
        env=child_env(),
        check=True,
        capture_output=True,
        timeout=300,
    )
    report = json.loads(out.read_text())
    assert report["actions_equal"], "act() must sample exactly what rsl-rl's act() samples"
    ours, theirs = report["losses"]
    for key in ours:
        assert ours[key] == pytest.approx(theirs[key], rel=1e-4, abs=1e-6), key
    # rsl-rl broadcasts the learning rate as float32; fused Adam rounds differently from the per-tensor loop
    assert report["learning_rates"][0] == pytest.approx(report["learning_rates"][1], rel=1e-6)
    assert report["max_param_diff"] < 1e-5


def test_rsl_rl_bootstraps_the_value_at_time_limits_of_ftrain_envs() -> None:
    """ftrain relies on rsl-rl's PPO for this: at a time-limit truncation (``extras["time_outs"]``), the stored
    reward gets ``gamma * V(s)`` added, V of the last observation before it (the final one is replaced by the reset);
    on other steps the reward is stored as it is. HalfCheetah never terminates, so every episode ends this way."""
    config = load_config(SMOKE, ["env.kwargs={max_episode_steps: 5}", "num_steps_per_env=7"])
    env = MujocoVecEnv(config.env.id, config.env.num_envs, seed=0, kwargs=config.env.kwargs)
    alg = build_ppo(config, env, RankInfo(0, 1, 0))
    obs, expected, time_outs = env.get_observations(), [], []
    with torch.inference_mode():
        for _ in range(config.num_steps_per_env):
            actions = alg.act(obs)
            values = alg.transition.values.squeeze(1).clone()
            obs, rewards, dones, extras = env.step(actions)
            time_outs.append(extras["time_outs"].clone())
            expected.append(rewards + config.algorithm.gamma * values * extras["time_outs"])
            alg.process_env_step(obs, rewards, dones, extras)
    assert [bool(t.all()) for t in time_outs] == [False] * 4 + [True] + [False] * 2
    assert torch.equal(alg.storage.rewards.squeeze(-1), torch.stack(expected))


@pytest.mark.parametrize("reshuffle", [False, True])
def test_minibatches_cover_the_rollout_every_epoch_in_one_or_fresh_orders(reshuffle: bool) -> None:
    overrides = ["algorithm.num_learning_epochs=3", f"algorithm.reshuffle_each_epoch={str(reshuffle).lower()}"]
    config = load_config(SMOKE, overrides)
    env = MujocoVecEnv(config.env.id, config.env.num_envs, seed=0, kwargs=config.env.kwargs)
    alg = build_ppo(config, env, RankInfo(0, 1, 0))
    rollout(alg, env, config.num_steps_per_env)
    batch = alg._local_rollout()
    batches = [each.actor_obs for each in mini_batches(alg, batch, alg._sample_orders(batch.samples))]
    per_epoch = len(batches) // 3
    epochs = [torch.cat(batches[i * per_epoch : (i + 1) * per_epoch]) for i in range(3)]
    everything = alg.actor.obs_normalizer(alg.storage.observations["policy"].flatten(0, 1))
    for epoch in epochs:
        assert torch.equal(epoch.sort(dim=0).values, everything.sort(dim=0).values)
    assert torch.equal(epochs[0], epochs[1]) == torch.equal(epochs[1], epochs[2]) == (not reshuffle)


def test_ranks_hold_every_sample_of_the_global_batch_once_where_one_rank_would() -> None:
    """Generated layouts: a global row ``step x total_envs + env`` is held by exactly one rank of a data-parallel
    update, at the row where that rank stores the step of that environment."""
    generator = torch.Generator().manual_seed(0)
    cases = 0
    for _ in range(50):
        ranks, envs, steps = (
            int(torch.randint(low, high, (1,), generator=generator)) for low, high in ((1, 9), (1, 6), (1, 5))
        )
        total = ranks * envs
        rows = torch.randperm(total * steps, generator=generator)[: int(torch.randint(1, total * steps + 1, (1,)))]
        # what each row holds: its (step, global env) pair, stored as each rank stores its own environments
        held_by = []
        for rank in range(ranks):
            local = torch.tensor([[step, rank * envs + env] for step in range(steps) for env in range(envs)])
            batch = Rollout([local], torch.zeros(total * steps), envs, rank * envs, total)
            mine, where = batch.held(rows)
            assert torch.equal(local[where], torch.stack([mine // total, mine % total], dim=1))
            held_by.append(mine)
        assert torch.equal(torch.cat(held_by).sort().values, rows.sort().values)
        cases += 1
    print(f"{cases} layouts checked")


@pytest.mark.slow  # worker processes under torchrun
@pytest.mark.parametrize(
    ("ranks", "overrides"),
    [
        (2, ["algorithm.schedule=adaptive"]),
        (2, ["algorithm.schedule=fixed", "algorithm.reshuffle_each_epoch=true", "shared_memory_all_reduce=false"]),
        (4, ["algorithm.schedule=adaptive"]),
    ],
    ids=["shm-adaptive", "gloo-fixed", "teams-of-2"],
)
def test_split_update_is_one_ranks_update_of_the_whole_batch(tmp_path, ranks: int, overrides: list[str]) -> None:
    """The first half of the ranks learns the actor and the second half the critic: every rank must end with the state
    that one rank holding every environment reaches from the same start, on the same batch in the same order; bit for
    bit at two ranks, and to rounding at four (each team then averages its two halves of every minibatch)."""
    out = tmp_path / "split.pt"
    worker = str(REPO / "tests" / "train" / "split_worker.py")
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}"]
    subprocess.run([*launcher, worker, str(out), *overrides], cwd=REPO, env=child_env(), check=True, timeout=300)
    saved = torch.load(out, weights_only=True)
    ends = [torch.load(f"{out}.{rank}", weights_only=True) for rank in range(ranks)]
    envs = 4 * ranks  # the smoke config's 4 environments, of every rank
    config = load_config(SMOKE, [*overrides, f"env.num_envs={envs}"])
    alone = build_ppo(config, MujocoVecEnv(config.env.id, envs, seed=0, kwargs=config.env.kwargs), RankInfo(0, 1, 0))
    load_learned_state(alone, saved["start"]["models"], saved["start"]["learning_rate"])
    fields = saved["start"]["fields"]
    assert fields[0].shape[0] == envs * config.num_steps_per_env
    alone._local_rollout = lambda: Rollout(fields, saved["start"]["advantages"], envs, 0, envs)
    alone.shared_generator.set_state(saved["start"]["shared_rng"])  # the same sample orders
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the ranks ran: another thread count sums a product in another order
    try:
        losses = alone.update()
    finally:
        torch.set_num_threads(threads)
    expected = alone.save()
    same = torch.equal if ranks == 2 else lambda ours, theirs: torch.allclose(ours, theirs, rtol=1e-4, atol=1e-6)
    for end in ends:
        assert learned_tensors(end["models"]).keys() == learned_tensors(expected).keys()
        for key, tensor in learned_tensors(expected).items():
            assert same(learned_tensors(end["models"])[key], tensor), key
            assert torch.equal(learned_tensors(end["models"])[key], learned_tensors(ends[0]["models"])[key]), key
        assert end["losses"] == pytest.approx(losses, rel=1e-6 if ranks == 2 else 1e-3)
        assert end["learning_rate"] == pytest.approx(alone.learning_rate, rel=0 if ranks == 2 else 1e-6)
    if "algorithm.schedule=adaptive" in overrides:  # the rate moved with the KL of the minibatches
        assert alone.learning_rate != saved["start"]["learning_rate"]
    assert saved["end"]["losses"]["value"] > 0 and saved["end"]["losses"]["entropy"] != 0


def learned_tensors(models: dict) -> dict[str, torch.Tensor]:
    """Models and Adam's state from ``alg.save()``, by name."""
    tensors = {
        f"{key}/{name}": value
        for key in ("actor_state_dict", "critic_state_dict")
        for name, value in models[key].items()
    }
    for index, state in models["optimizer_state_dict"]["state"].items():
        tensors |= {f"adam/{index}/{name}": value for name, value in state.items()}
    return tensors
