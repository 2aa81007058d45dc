"""Evaluation and policy snapshots in real training runs: no effect on what is learned, keep-best by eval_return,
verified snapshots with their own retention, and snapshots redone after a resume."""

from __future__ import annotations

import json
import math
import random
import shutil
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from ftrain.cli import main
from ftrain.comm.group import RankInfo
from ftrain.config import load_config
from ftrain.errors import UserError
from ftrain.policy import snapshots
from ftrain.policy.export import sample_observations
from ftrain.policy.load import load_policy
from ftrain.policy.model import OBS_GROUP, actor_actions, build_actor
from ftrain.policy.play import play
from ftrain.policy.robot import make_env
from ftrain.policy.rollout import rollout
from ftrain.train.evaluation import episode_share

from helpers import SMOKE, final_manifest, manifests, metrics_by_iteration, run_train

EVAL = ("eval.every=3", "eval.episodes=3", "checkpoint.best_metric=eval_return", "checkpoint.keep_last=1")
SNAPSHOTS = ("snapshots.every=2", "snapshots.keep_last=2")
FILES = {"policy.pt", "policy.onnx", "actor.pt", "lineage.json"}
RANKS = 2
"""Evaluation is shared by the ranks (2 episodes on rank 0, 1 on rank 1) and snapshots are rank 0's: neither may make
a rank wait forever or learn otherwise."""


pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def runs(tmp_path_factory, reference_run) -> Path:
    """The smoke run (8 iterations, a checkpoint every 2, 2 ranks) with evaluation and snapshots (supervised), and
    without (the shared reference run)."""
    root = tmp_path_factory.mktemp("runs")
    run_train(root / "eval", *EVAL, *SNAPSHOTS, ranks=RANKS, supervised=True)
    (root / "plain").symlink_to(reference_run(8))
    return root


def snapshot_url(run: Path, step: int) -> str:
    return str(run / "policies" / f"step-{step:09d}")


def lineage(run: Path, step: int) -> dict:
    return json.loads((Path(snapshot_url(run, step)) / "lineage.json").read_text())


def test_evaluation_and_snapshots_leave_training_unchanged(runs) -> None:
    assert final_manifest(runs / "eval")["state_sha256"] == final_manifest(runs / "plain")["state_sha256"]
    evaluated = metrics_by_iteration(runs / "eval")
    for row in evaluated.values():
        row.pop("eval_return")
        row.pop("eval_time")
    assert evaluated == metrics_by_iteration(runs / "plain")


def test_eval_return_every_n_iterations_and_at_the_end_feeds_keep_best(runs) -> None:
    run = runs / "eval"
    scores = {it: float(row["eval_return"]) for it, row in metrics_by_iteration(run).items()}
    assert [it for it, score in scores.items() if not math.isnan(score)] == [3, 6, 8]  # every 3, and the last
    eval_times = {it: float(row["eval_time"]) for it, row in metrics_by_iteration(run).items()}
    assert [it for it, seconds in eval_times.items() if seconds > 0] == [3, 6, 8]
    best = max((6, 8), key=scores.get)  # of the steps saved (every 2) and evaluated
    kept = manifests(run)
    assert set(kept) == {8, best}, "keep_last=1 and keep_best=1 by eval_return"
    for step, manifest in kept.items():
        assert manifest["metrics"]["eval_return"] == scores[step]

    # the score is a function of the weights alone: ``play`` of the step, with the evaluation's episodes and seed,
    # one after another in one env, returns it exactly (2 ranks evaluated them: 2 episodes on rank 0, 1 on rank 1)
    policy = load_policy(str(run / "checkpoints" / f"step-{best:09d}"))
    played = play(policy, policy.config.eval.episodes, seed=policy.config.eval.seed)
    assert sum(played.returns) / len(played.returns) == scores[best]


def test_an_episode_scores_alike_on_any_rank_beside_any_others_and_in_play() -> None:
    """Generated cases (episodes, world size, seed): the episodes evaluated as the ranks share them (a block each,
    at once) return, bit for bit, what they return all on one rank and one after another in one env as ``play``
    runs them, since each keeps its row of one batch of all (``rollout``'s ``rows``). Without the rows an episode
    acts in batches of other shapes, which round otherwise: the cases where that changed a return are counted too, so
    that the property is seen to be at stake."""
    rng = random.Random()
    torch.manual_seed(rng.randrange(2**31))
    config = load_config(SMOKE)
    probe = make_env(config.env)
    obs, actions = probe.observation_space.shape[0], probe.action_space.shape[0]
    actor = build_actor(config, TensorDict({OBS_GROUP: torch.zeros(1, obs)}, batch_size=[1]), actions)
    with torch.no_grad():
        for parameter in actor.parameters():
            parameter.mul_(4)  # a policy that acts, not one near zero
    act = lambda batch: actor_actions(actor, batch)  # noqa: E731
    envs = [make_env(config.env) for _ in range(8)]
    checked = changed = 0
    for _ in range(12):
        episodes, world, seed = rng.randint(2, 8), rng.randint(2, 4), rng.randrange(10_000)
        once = [e.ret for e in rollout(envs[:episodes], act, episodes, seed, rows=(0, episodes))]
        shared, unplaced = [], []
        for rank in range(world):
            first, count = episode_share(episodes, RankInfo(rank, world, rank))
            if count:
                placed = rollout(envs[:count], act, count, seed + first, rows=(first, episodes))
                shared += [e.ret for e in placed]
                unplaced += [e.ret for e in rollout(envs[:count], act, count, seed + first)]
        alone = [e.ret for e in rollout(probe, act, episodes, seed, rows=(0, episodes))]
        assert shared == once == alone, (episodes, world, seed)
        checked += 1
        changed += unplaced != once
    print(f"{checked} cases checked; without rows, {changed} of them returned otherwise")
    assert changed > 0


@pytest.mark.filterwarnings("ignore:`torch.jit.load` is deprecated:DeprecationWarning")
def test_snapshots_are_verified_with_their_own_retention(runs, capsys, monkeypatch) -> None:
    run = runs / "eval"
    assert sorted(p.name for p in (run / "policies").iterdir()) == ["step-000000006", "step-000000008"]
    checkpoint = final_manifest(run)
    for step in (6, 8):
        _, _, manifest = snapshots.open_snapshot(snapshot_url(run, step))
        assert set(manifest["files"]) == FILES and manifest["config_hash"] == checkpoint["config_hash"]
        story = lineage(run, step)
        assert story["step"] == step and story["config_hash"] == checkpoint["config_hash"]
        assert story["committed_checkpoint"]["step"] in (step - 6, step - 4, step - 2)  # two saves may be in flight
        assert story["metrics"]["eval_return"] == float(metrics_by_iteration(run)[step]["eval_return"])
    assert lineage(run, 8)["state_sha256"] == checkpoint["state_sha256"], "the same training state as step 8"

    snapshot = load_policy(snapshot_url(run, 8))
    trained = load_policy(str(run))
    assert (snapshot.step, snapshot.digest) == (8, checkpoint["state_sha256"])
    obs = sample_observations(trained)
    assert torch.equal(snapshot.act(obs), trained.act(obs))
    with torch.inference_mode():
        scripted = torch.jit.load(Path(snapshot_url(run, 8)) / "policy.pt")(obs)
    torch.testing.assert_close(scripted, trained.act(obs), atol=1e-5, rtol=1e-5)

    assert main(["play", snapshot_url(run, 8)]) == 0
    assert "episode 1: return" in capsys.readouterr().out

    onnx_file = Path(snapshot_url(run, 6)) / "policy.onnx"
    data = bytearray(onnx_file.read_bytes())
    data[-1] ^= 0xFF
    onnx_file.write_bytes(bytes(data))
    with pytest.raises(UserError, match=r"policy snapshot .*step-000000006 does not verify \(policy.onnx: sha256"):
        load_policy(snapshot_url(run, 6))
    with pytest.raises(UserError, match=r"policy snapshot .*step-000000006 does not verify \(policy.onnx: sha256"):
        load_policy(str(onnx_file))  # the file itself is as verified as its snapshot (it played, unchecked)
    assert load_policy(str(Path(snapshot_url(run, 8)) / "policy.onnx")).exported == "onnx"  # an intact one plays
    capsys.readouterr()
    assert main(["ckpt", "verify", str(run)]) == 1  # the checkpoints, then the snapshots: verified alike
    out = capsys.readouterr().out.splitlines()
    assert out[:3] == [
        "step 8: ok",
        "one history: 1 step on one line of descent, 0 superseded",
        "1 of 1 committed step verified",
    ]
    assert out[3:5] == ["policy snapshot 8: ok", "policy snapshot 6: FAILED"], out  # newest first, as ckpt ls
    assert out[5].startswith("  policies/step-000000006/policy.onnx: sha256 mismatch: "), out
    assert out[6:] == ["1 of 2 committed policy snapshots verified"], out
    monkeypatch.chdir(run / "policies")  # named from inside policies/, as a checkpoint step may be from checkpoints/
    assert main(["ckpt", "verify", "step-000000008"]) == 0
    assert capsys.readouterr().out.splitlines() == [
        "policy snapshot 8: ok",
        "1 of 1 committed policy snapshot verified",
    ]


def test_a_resumed_run_redoes_the_snapshots_past_its_checkpoint(runs, tmp_path) -> None:
    """Lose the newest checkpoint: the run resumes from an older one and writes the snapshots it redoes afresh."""
    run = tmp_path / "run"
    shutil.copytree(runs / "eval", run)
    before = lineage(run, 8)
    shutil.rmtree(run / "checkpoints" / "step-000000008")
    result = run_train(run, *EVAL, *SNAPSHOTS, "iterations=10", ranks=RANKS, supervised=True)
    assert "deleting policy snapshot step 8 (verified)" in result.stdout
    assert sorted(p.name for p in (run / "policies").iterdir()) == ["step-000000008", "step-000000010"]
    redone = lineage(run, 8)
    assert redone["state_sha256"] == before["state_sha256"], "the redone iterations learn exactly the same"
    snapshots.open_snapshot(snapshot_url(run, 10))
