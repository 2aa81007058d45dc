"""The line that says what a run will run: ranks and hosts, the update's split or why it is data-parallel, the
transport, the global batch; and a real 4-rank run's first line and run.json."""

from __future__ import annotations

import json
import subprocess

import pytest

from ftrain.comm.collectives import Comm
from ftrain.comm.group import RankInfo
from ftrain.config import load_config
from ftrain.train.topology import RUN_FILE, describe, summary

from helpers import REPO, SMOKE, child_env, supervise_command


def line(world: int, *overrides: str, hosts: list[str] | None = None) -> str:
    config = load_config(SMOKE, ["env.num_envs=4", *overrides])
    info = RankInfo(0, world, 0)
    gloo_only = Comm(info, list(range(world)), None, None, print)
    return summary(describe(config, info, hosts or ["a"] * world, gloo_only))


def test_an_even_number_of_ranks_says_which_learn_the_actor_and_which_the_critic() -> None:
    assert "update split: actor on ranks 0-1, critic on ranks 2-3, data-parallel within each team of 2 |" in line(4)
    assert "update split: actor on rank 0, critic on rank 1 |" in line(2)
    assert line(4).endswith("global batch 256 steps (4 ranks x 4 envs x 16 steps)")


def test_a_data_parallel_update_says_why() -> None:
    assert "update data-parallel (3 ranks: a split needs an even number) |" in line(3)
    assert "update data-parallel (split_update=false) |" in line(4, "split_update=false")
    assert "transport gloo (shared_memory_all_reduce=false)" in line(2, "shared_memory_all_reduce=false")
    alone = line(1)
    assert alone.startswith("1 rank on 1 host (rank 0 on a) | update on one rank | transport none (one process)")


def test_ranks_on_several_hosts_are_named_by_host() -> None:
    assert line(4, hosts=["a", "a", "b", "b"]).startswith("4 ranks on 2 hosts (ranks 0-1 on a, ranks 2-3 on b) |")


@pytest.mark.slow
def test_a_4_rank_run_says_first_how_its_update_is_split(tmp_path) -> None:
    storage = tmp_path / "run"  # supervised: its workers fork from one process that imported torch, not four
    result = subprocess.run(
        supervise_command(storage, "iterations=1", "log.console=true", ranks=4),
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.splitlines()  # the workers' (the supervisor's own lines go to stderr)
    assert lines, result.stderr[-3000:]
    first = lines[0]
    assert first.startswith("[ftrain] 4 ranks on 1 host (ranks 0-3 on ")
    assert "update split: actor on ranks 0-1, critic on ranks 2-3" in first
    assert "transport shared memory (one host)" in first
    run = json.loads((storage / RUN_FILE).read_text())
    assert run["update"] == {"kind": "split", "actor": [0, 1], "critic": [2, 3]} and run["global_batch"]["ranks"] == 4
