"""FusedPPO is rsl-rl's PPO with cheaper synchronisation: same actions, same update, on 1 and 2 real ranks."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from helpers import REPO, child_env


@pytest.mark.parametrize("ranks", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_fused_ppo_matches_rsl_rl_ppo(tmp_path, ranks: int) -> None:
    out = tmp_path / "report.json"
    launcher = [sys.executable]
    if ranks > 1:
        launcher += ["-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}"]
    subprocess.run(
        [*launcher, str(REPO / "tests" / "train" / "equivalence_worker.py"), str(out)],
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
