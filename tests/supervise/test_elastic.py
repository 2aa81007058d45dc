"""Elastic training (``--nnodes MIN:MAX``): several supervised nodes on 127.0.0.1, each a real supervisor, torchrun
and worker; a node is lost by killing its whole process tree at once, like a machine that lost power."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from ftrain.ckpt.format import verify_step
from ftrain.ckpt.storage import Storage
from ftrain.errors import EXIT_RENDEZVOUS_TIMEOUT
from ftrain.supervise.auth import SECRET_ENV
from ftrain.supervise.coordinator import Plan, rendezvous_args
from ftrain.supervise.options import EXIT_TOO_FEW_NODES, Nodes, SupervisorOptions

from helpers import (
    REPO,
    SMOKE,
    TESTS,
    child_env,
    events,
    final_manifest,
    finish,
    free_port,
    kill_tree,
    launch,
    manifests,
    wait_for,
)

pytestmark = pytest.mark.slow

HERE = Path(__file__).resolve().parent
INTERVAL = 5
PACE = "hooks=[{target: 'probe_hooks:PacingHook', kwargs: {seconds: 0.15}}]"
"""Iterations of at least 0.15 s: a run that lasts while nodes come and go, however fast the machine."""


def start_node(storage: Path, node: int, nnodes: str, endpoint: str, *overrides: str, **kw: str) -> subprocess.Popen:
    """One node of an elastic run: ``ftrain supervise`` with one rank; output in ``<storage>.node<N>.log``."""
    options = {"rejoin_timeout": "3", "rdzv_timeout": "60", "backoff_initial": "0.2", "stop_grace": "20", **kw}
    command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "1", "--nnodes", nnodes]
    command += ["--node-rank", str(node), "--rdzv-endpoint", endpoint]
    command += [f"--{key.replace('_', '-')}={value}" for key, value in options.items()]
    command += [SMOKE, "--storage", str(storage), f"checkpoint.interval={INTERVAL}", "dist_timeout=10"]
    command += ["log.console=false", PACE, *overrides]
    output = open(f"{storage}.node{node}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
    env = child_env({SECRET_ENV: "ftrain-test-elastic-secret", "PYTHONPATH": str(TESTS)})
    return launch(command, cwd=REPO, env=env, stdout=output, stderr=subprocess.STDOUT)


def node_events(storage: Path, name: str, node: int) -> list[dict]:
    return [event for event in events(storage) if event["event"] == name and event.get("node") == node]


def wait_resizes(storage: Path, nodes: list[int], count: int, timeout: float = 180) -> None:
    def done() -> bool:
        return all(len(node_events(storage, "resize", node)) >= count for node in nodes)

    wait_for(done, f"{count} resize events on nodes {nodes}", timeout=timeout, interval=0.2)


def training_world(storage: Path, world: int) -> bool:
    """Whether a world of ``world`` ranks trains on node 0 and has committed a checkpoint."""
    beats = (storage / "heartbeat" / "node-0").glob("rank-*.json")
    training = any(
        f'"world": {world}' in path.read_text() and '"phase": "rollout"' in path.read_text() for path in beats
    )
    return training and bool(manifests(storage))


def test_three_nodes_shrink_to_two_when_one_is_lost_and_grow_back_when_it_returns(tmp_path) -> None:
    storage, endpoint, iterations = tmp_path / "run", f"127.0.0.1:{free_port()}", 260
    nodes = [start_node(storage, node, "2:3", endpoint, f"iterations={iterations}") for node in range(3)]
    wait_for(lambda: training_world(storage, 3), "a world of 3 ranks training", timeout=180, interval=0.2)
    kill_tree(nodes[2])  # node 2 gone for good: its supervisor, torchrun and worker at once
    wait_resizes(storage, [0, 1], 1)
    nodes[2] = start_node(storage, 2, "2:3", endpoint, f"iterations={iterations}")  # the machine is back
    wait_resizes(storage, [0, 1], 2)
    assert [finish(node, timeout=300) for node in nodes] == [0, 0, 0]

    manifest = final_manifest(storage)
    assert manifest["step"] == iterations and manifest["world_size"] == 3
    worlds = [world for _, world in manifest["world_sizes"]]
    assert worlds == [3, 2, 3], manifest["world_sizes"]
    for node in (0, 1):
        shrink, grow = node_events(storage, "resize", node)
        assert (shrink["old_world"], shrink["new_world"], shrink["new_nodes"]) == (3, 2, [0, 1]), shrink
        assert shrink["why"] == "node 2 lost" and shrink["lost"] <= INTERVAL, shrink
        assert (grow["old_world"], grow["new_world"], grow["new_nodes"]) == (2, 3, [0, 1, 2]), grow
        assert grow["why"] == "node 2 joined" and grow["lost"] == 0, grow
        assert grow["downtime"] < 60 and shrink["downtime"] < 60
    verify = subprocess.run(
        [sys.executable, "-m", "ftrain", "ckpt", "verify", str(storage)], cwd=REPO, env=child_env(), text=True
    )
    assert verify.returncode == 0


def test_below_min_nodes_wait_then_exit_6_and_keep_every_checkpoint(tmp_path) -> None:
    storage, endpoint = tmp_path / "run", f"127.0.0.1:{free_port()}"
    nodes = [start_node(storage, node, "2:3", endpoint, "iterations=400", rdzv_timeout="15") for node in range(3)]
    wait_for(lambda: training_world(storage, 3), "a world of 3 ranks training", timeout=180, interval=0.2)
    kill_tree(nodes[1])
    kill_tree(nodes[2])
    assert finish(nodes[0], timeout=180) == EXIT_TOO_FEW_NODES == EXIT_RENDEZVOUS_TIMEOUT
    assert len(node_events(storage, "too_few_nodes", 0)) == 1
    console = Path(f"{storage}.node0.log").read_text()
    named = re.search(r"newest step (\d+)\): start the missing nodes and run the same command again", console)
    assert named and int(named[1]) in manifests(storage), console  # a committed step (a newer one may follow it)
    checkpoints = Storage.open(str(storage))
    for step in manifests(storage):  # every committed step verifies (a save the kill cut short never committed)
        assert verify_step(checkpoints, step, full=True).ok, step


def test_eight_nodes_lose_three_at_once_continue_with_five_and_take_them_back(tmp_path) -> None:
    """A scale simulation for correctness, 8 nodes x 1 rank of the smoke config on this machine."""
    storage, endpoint, iterations = tmp_path / "run", f"127.0.0.1:{free_port()}", 200
    extra = {"rejoin_timeout": "5", "startup_grace": "600"}
    nodes = [start_node(storage, node, "4:8", endpoint, f"iterations={iterations}", **extra) for node in range(8)]
    wait_for(lambda: training_world(storage, 8), "a world of 8 ranks training", timeout=400, interval=0.5)
    for node in (5, 6, 7):
        kill_tree(nodes[node])
    wait_resizes(storage, [0, 1, 2, 3, 4], 1, timeout=400)
    for node in (5, 6, 7):
        nodes[node] = start_node(storage, node, "4:8", endpoint, f"iterations={iterations}", **extra)
    wait_for(lambda: training_world(storage, 8), "a world of 8 ranks again", timeout=400, interval=0.5)
    assert [finish(node, timeout=600) for node in nodes] == [0] * 8
    manifest = final_manifest(storage)
    assert manifest["step"] == iterations and manifest["world_size"] == 8
    worlds = [world for _, world in manifest["world_sizes"]]
    assert worlds[:2] == [8, 5] and worlds[-1] == 8, manifest["world_sizes"]  # the three may rejoin one by one
    shrink, *grows = node_events(storage, "resize", 0)
    assert (shrink["old_world"], shrink["new_world"], shrink["why"]) == (8, 5, "node 5, 6, 7 lost"), shrink
    assert grows and grows[-1]["new_world"] == 8 and all(grow["lost"] == 0 for grow in grows), grows


def torchrun_node(node: int, port: int, log: Path, share_store: bool) -> subprocess.Popen:
    """A bare elastic torchrun node (1:2 nodes, the rendezvous arguments the supervisor gives) of ``elastic_worker``."""
    options = SupervisorOptions(node_rank=node, rejoin_timeout=2, rdzv_timeout=60)
    arguments = rendezvous_args(Plan("test", 0, port), Nodes(2, 1, ("127.0.0.1", 0)), options)
    command = [sys.executable, "-m", "torch.distributed.run", "--nproc-per-node=1", "--max-restarts=0", *arguments]
    env = child_env({"TORCH_DISABLE_SHARE_RDZV_TCP_STORE": "0" if share_store else "1"})
    output = log.open("ab")
    return launch([*command, str(HERE / "elastic_worker.py")], env=env, stdout=output, stderr=subprocess.STDOUT)


@pytest.mark.parametrize("share_store", [False, True])
def test_a_late_node_grows_torchruns_world_only_without_the_shared_agent_store(tmp_path, share_store) -> None:
    """Why the supervisor sets ``TORCH_DISABLE_SHARE_RDZV_TCP_STORE=1``: with torch's default, the workers that
    torchrun restarts when a node joins never get past ``init_process_group``."""
    port, first, second = free_port(), tmp_path / "node0.log", tmp_path / "node1.log"
    nodes = [torchrun_node(0, port, first, share_store)]
    wait_for(lambda: "world 1 rank 0" in first.read_text(errors="replace"), "a world of one", timeout=60)
    nodes.append(torchrun_node(1, port, second, share_store))
    try:
        grew = wait_for(lambda: "world 2" in second.read_text(errors="replace"), "a world of two", timeout=30)
    except AssertionError:
        grew = False
    for node in nodes:
        kill_tree(node)
    assert bool(grew) is not share_store, (first.read_text(errors="replace"), second.read_text(errors="replace"))
