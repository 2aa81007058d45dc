"""A 3-node elastic run on etcd (``--nnodes 2:3``) across simulated machines: each node in a network namespace of
its own with its own address (``netns.Bed``, fixture ``network``), etcd on a fourth; the storage a local directory
that every node sees, as a shared filesystem. Each node says which address is its own (``--local-addr``): the
machines share one hostname, which resolves to 127.0.0.1, as in many containers."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ftrain import procfs

from elastic_nodes import (
    KEEP_ALL,
    PACING,
    CommitHold,
    assert_fenced_history,
    etcd,
    rank_zero,
    resizes,
    start_node,
    three_etcd_nodes,
    verify_cli,
    wait_resizes,
    worlds,
)
from helpers import final_manifest, finish, manifests, wait_for
from netns import DEVICE, Bed

pytestmark = pytest.mark.cluster


def hosts(bed: Bed) -> list[dict]:
    """``three_etcd_nodes``' nodes on hosts 0-2, each naming its own address."""
    return [{"launcher": bed.launcher(host), "local_addr": bed.address(host)} for host in range(3)]


def worker_env(storage, world: int, supervisor: int) -> dict[str, str]:
    """The environment torchrun gave rank 0's worker in a world of ``world`` ranks, below ``supervisor``: /proc's view
    of the process torchrun started for it (a warm worker is forked from the pool, whose environment /proc shows for
    it; the stand-in torchrun started holds the worker's)."""
    wait_for(lambda: rank_zero(storage, world), f"rank 0 of a world of {world}")
    for pid in procfs.descendants(supervisor):
        env = dict(item.partition("=")[::2] for item in procfs.read(pid, "environ").decode().split("\0") if item)
        if env.get("RANK") == "0" and env.get("WORLD_SIZE") == str(world):
            return env
    raise AssertionError(f"no process below {supervisor} has the environment of rank 0 of {world}")


def test_node_0s_machine_loses_every_process_and_the_others_finish_at_world_2(tmp_path, network) -> None:
    """The node whose worker is rank 0 hosts the workers' store, on its own address: every process of its machine
    dies at once, and the two others go on at world size 2 and finish."""
    bed, endpoint = network
    storage, iterations = tmp_path / "run", 50
    nodes, lost, index = three_etcd_nodes(storage, endpoint, iterations, hosts=hosts(bed))
    # the store on rank 0's own address, gloo on each host's interface to the bridge
    env = worker_env(storage, 3, nodes[index].pid)
    assert (env["MASTER_ADDR"], env["GLOO_SOCKET_IFNAME"]) == (bed.address(index), DEVICE), env
    assert nodes[index].pid in bed.kill(index)
    nodes[index].wait()
    wait_for(lambda: not bed.pids(index), "nothing left on the lost machine", timeout=30)
    survivors = [proc for proc in nodes if proc is not nodes[index]]
    assert [finish(proc, timeout=150) for proc in survivors] == [0, 0]

    manifest = final_manifest(storage)
    assert manifest["step"] == iterations and manifest["world_size"] == 2
    assert worlds(manifest) == [3, 2], manifest["world_sizes"]
    for node in sorted({0, 1, 2} - {lost}):
        (shrink,) = resizes(storage, node)
        assert shrink["why"] == f"node {lost} lost", shrink
    assert_fenced_history(storage)
    assert verify_cli(storage) == 0


def test_a_node_cut_off_past_the_timeouts_is_left_behind_fenced_and_rejoins_when_the_link_is_back(
    tmp_path, network
) -> None:
    """A partition: the node whose worker is rank 0 (the one that commits) holds a commit (once armed) with the shards
    gathered and the fence not yet read (``HoldCommitHook``), and its link goes down. The two others shrink to world
    2 and commit at a newer generation; then the held commit goes on, still cut off, and the fence itself refuses it
    (its line says so: no failed gather stopped it first). The link comes back, the node rejoins (world 3 again),
    and no commit of its old generation lands after theirs."""
    bed, endpoint = network
    storage, iterations, hold = tmp_path / "run", 150, CommitHold(tmp_path)
    nodes, cut, index = three_etcd_nodes(
        storage, endpoint, iterations, KEEP_ALL, hooks=(PACING, hold.hook), hosts=hosts(bed)
    )
    assert hold.held() in procfs.descendants(nodes[index].pid)
    bed.link(index, up=False)
    others = sorted({0, 1, 2} - {cut})
    wait_resizes(storage, others, 1, timeout=90)
    newer = lambda: json.loads((storage / "FENCE.json").read_text())["attempt"] > 0  # noqa: E731
    wait_for(newer, "a commit of the world of 2", timeout=60, interval=0.2)
    hold.release()
    console = Path(f"{storage}.node{index}.log")
    refused = wait_for(lambda: hold.refused(console), "the fence refusing the held commit")
    bed.link(index, up=True)
    wait_resizes(storage, others, 2, timeout=120)
    assert [finish(proc, timeout=180) for proc in nodes] == [0, 0, 0]

    manifest = final_manifest(storage)
    assert manifest["step"] == iterations and manifest["world_size"] == 3
    assert worlds(manifest) == [3, 2, 3], manifest["world_sizes"]
    for node in others:
        shrink, grow = resizes(storage, node)
        assert (shrink["new_world"], grow["new_world"]) == (2, 3), (shrink, grow)
    history = assert_fenced_history(storage)
    print(f"cut node {cut}: refused step {refused[1]}; committed (step, generation): {history}")
    assert history[0][1] == 0 and all(generation > 0 for step, generation in history if step >= int(refused[1]))
    assert verify_cli(storage) == 0


DELAY_MS = 20


def connect_seconds(bed: Bed, host: int, endpoint: str) -> float:
    """How long a TCP connection from ``host`` to ``endpoint`` takes to open: one round trip."""
    address, _, port = endpoint.rpartition(":")
    probe = (
        "import socket, time; start = time.monotonic(); "
        f"socket.create_connection(({address!r}, {port}), timeout=5); print(time.monotonic() - start)"
    )
    command = [*bed.launcher(host), sys.executable, "-c", probe]
    return float(subprocess.run(command, capture_output=True, text=True, check=True).stdout)


@pytest.mark.parametrize("network", [DELAY_MS], indirect=True)
def test_with_20_ms_on_every_link_training_runs_and_checkpoints(tmp_path, network) -> None:
    """Every frame between two hosts arrives 20 ms late (a round trip 40 ms longer, as between data centres): the
    rendezvous, the workers' store and gloo's collectives all cross it, and the run trains, checkpoints and
    finishes at world size 3 with every step verifying. ``--nnodes 3:3``: the rendezvous waits for all three (at
    ``2:3`` a node that starts late under load is a grow from 2, another test's subject)."""
    bed, endpoint = network
    round_trip = connect_seconds(bed, 0, endpoint)
    print(f"a TCP connect from host 0 to etcd takes {1000 * round_trip:.0f} ms")
    assert round_trip >= 2 * DELAY_MS / 1000
    storage, iterations = tmp_path / "run", 10
    overrides = (f"iterations={iterations}",)
    nodes = [start_node(storage, host, "3:3", etcd(endpoint), *overrides, **hosts(bed)[host]) for host in range(3)]
    assert [finish(proc, timeout=180) for proc in nodes] == [0, 0, 0]
    manifest = final_manifest(storage)
    assert (manifest["step"], manifest["world_size"], manifest["world_sizes"]) == (iterations, 3, [[0, 3]])
    assert len(manifests(storage)) >= 2  # more than one checkpoint committed across the slow links
    assert verify_cli(storage) == 0
