"""Nodes of an elastic run for the tests (``tests/supervise/test_elastic.py`` on 127.0.0.1, ``tests/cluster`` in
network namespaces): each a real ``ftrain supervise`` with one rank, and what their storage and events say."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

from ftrain import procfs
from ftrain.heartbeat import read_heartbeats
from ftrain.supervise.auth import SECRET_ENV

from helpers import REPO, SMOKE, TESTS, child_env, events, launch, manifests, probe_hook, wait_for

INTERVAL = 5
PACING = probe_hook("PacingHook", seconds=0.15)
"""Iterations of at least 0.15 s: a run that lasts while nodes come and go, however fast the machine."""


def etcd(endpoint: str) -> list[str]:
    """The node options of an etcd-v2 run: the same on every node."""
    return ["--rdzv-backend", "etcd-v2", "--rdzv-endpoint", endpoint, "--rdzv-id", "test-run"]


def start_node(
    storage: Path,
    node: int,
    nnodes: str,
    rendezvous: list[str],
    *overrides: str,
    hooks: Sequence[str] = (PACING,),
    launcher: Sequence[str] = (),
    env: dict[str, str] | None = None,
    **kw: str,
) -> subprocess.Popen:
    """One node of an elastic run: ``ftrain supervise`` with one rank, ``rendezvous`` its node options (``c10d`` or
    ``etcd``), ``hooks`` the training hooks; ``launcher`` comes before the command (``ip netns exec NAME``: the
    process keeps its pid), ``env`` adds to the environment; output in ``<storage>.node<N>.log``."""
    options = {"rejoin_timeout": "3", "rdzv_timeout": "60", "backoff_initial": "0.2", "stop_grace": "20", **kw}
    command = [*launcher, sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "1", "--nnodes", nnodes]
    command += [*rendezvous, *(f"--{key.replace('_', '-')}={value}" for key, value in options.items())]
    command += [SMOKE, "--storage", str(storage), f"checkpoint.interval={INTERVAL}", "dist_timeout=10"]
    command += ["log.console=false", f"hooks=[{', '.join(hooks)}]", *overrides]
    output = open(f"{storage}.node{node}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
    env = child_env({SECRET_ENV: "ftrain-test-elastic-secret", **(env or {}), "PYTHONPATH": str(TESTS)})
    return launch(command, cwd=REPO, env=env, stdout=output, stderr=subprocess.STDOUT)


def node_events(storage: Path, name: str, node: int) -> list[dict]:
    return [event for event in events(storage) if event["event"] == name and event.get("node") == node]


def resizes(storage: Path, node: int) -> list[dict]:
    """A node's resize events from its first shrink on (a late start's grows dropped, see ``worlds``)."""
    found = node_events(storage, "resize", node)
    return found[next((n for n, event in enumerate(found) if event["new_world"] < event["old_world"]), len(found)) :]


def wait_resizes(storage: Path, nodes: list[int], count: int, timeout: float = 300) -> None:
    def done() -> bool:
        return all(len(resizes(storage, node)) >= count for node in nodes)

    wait_for(done, f"{count} resize events on nodes {nodes}", timeout=timeout, interval=0.2)


def training_world(storage: Path, world: int, node: int = 0) -> bool:
    """Whether a world of ``world`` ranks trains on ``node`` and has committed a checkpoint (that world: a step of a
    smaller world that formed first does not count, or a node lost next may be lost before the supervisors know the
    world they resize from)."""
    beats = (storage / "heartbeat" / f"node-{node}").glob("rank-*.json")
    training = any(
        f'"world": {world}' in path.read_text() and '"phase": "rollout"' in path.read_text() for path in beats
    )
    return training and any(manifest["world_size"] == world for manifest in manifests(storage).values())


def rank_zero(storage: Path, world: int) -> tuple[int, int] | None:
    """The node (its number) whose worker is global rank 0 of a world of ``world`` ranks, and that worker's pid."""
    for directory in storage.glob("heartbeat/node-*"):
        beat = read_heartbeats(directory).get(0)
        if beat is not None and beat.world == world:
            return int(directory.name.removeprefix("node-")), beat.pid
    return None


def three_etcd_nodes(
    storage: Path,
    endpoint: str,
    iterations: int,
    *overrides: str,
    hooks: Sequence[str] = (PACING,),
    hosts: Sequence[dict] = ({},) * 3,
) -> tuple[list[subprocess.Popen], int, int]:
    """Three nodes of an etcd-v2 run (``--nnodes 2:3``) training at world size 3 with a checkpoint committed: their
    supervisors, and the number and list index of the node whose worker is rank 0 (etcd numbered the nodes 0, 1, 2
    as they started). ``hosts``: each node's options for ``start_node`` (``launcher``, ``local_addr``)."""
    overrides = (f"iterations={iterations}", *overrides)
    nodes = [
        start_node(storage, label, "2:3", etcd(endpoint), *overrides, hooks=hooks, **host)
        for label, host in enumerate(hosts)
    ]
    trains = lambda: any(training_world(storage, 3, node) for node in range(3))  # noqa: E731
    wait_for(trains, "a world of 3 ranks training", timeout=120, interval=0.2)
    node, worker = wait_for(lambda: rank_zero(storage, 3), "rank 0's node")
    return nodes, node, next(index for index, proc in enumerate(nodes) if worker in procfs.descendants(proc.pid))


def worlds(manifest: dict) -> list[int]:
    """A run's world sizes (``manifest["world_sizes"]``) from the world that first shrank on. Under load a node may
    start after the others began at the minimum, so that the run grows to its full world first: a late start, not
    what these tests do to it (the same for ``resizes``)."""
    sizes = [world for _, world in manifest["world_sizes"]]
    return sizes[next((n for n in range(len(sizes) - 1) if sizes[n + 1] < sizes[n]), len(sizes) - 1) :]


class CommitHold:
    """``probe_hooks.HoldCommitHook`` for a test of three nodes: ``hook`` goes into their hooks; ``held()`` arms it
    once the run trains at world 3 and returns the pid of the rank 0 that holds its next commit (the test must then
    pause or cut that node at once); ``release()`` lets the commit go on; ``refused(console)`` is the fence's line
    refusing it (a match: the step), None while there is none."""

    FENCED = re.compile(r"checkpoint step (\d+) refused: attempt 0 of generation \d+ is fenced off")

    def __init__(self, directory: Path) -> None:
        self.arm, self.marker, self.released = directory / "arm", directory / "held", directory / "release"
        self.hook = probe_hook("HoldCommitHook", arm=self.arm, marker=self.marker, release=self.released, world=3)

    def held(self) -> int:
        self.arm.touch()
        return int(wait_for(lambda: self.marker.exists() and self.marker.read_text(), "rank 0 holding its commit"))

    def release(self) -> None:
        self.released.touch()

    def refused(self, console: Path) -> re.Match | None:
        return self.FENCED.search(console.read_text())


def verify_cli(storage: Path) -> int:
    """``ftrain ckpt verify`` of a run's storage: its exit code (0: every committed step verifies)."""
    command = [sys.executable, "-m", "ftrain", "ckpt", "verify", str(storage)]
    return subprocess.run(command, cwd=REPO, env=child_env(), text=True).returncode


KEEP_ALL = "checkpoint.keep_last=1000"
"""Every committed step kept: the whole history of generations to check."""


def assert_fenced_history(storage: Path) -> list[tuple[int, int]]:
    """Fencing held: the committed steps' (generation, attempt) never go backwards in step order, all of one run,
    and ``FENCE.json`` names the newest; the ``(step, attempt)`` pairs."""
    steps = sorted(manifests(storage).items())
    keys = [(manifest["generation"], manifest["attempt"]) for _, manifest in steps]
    assert keys == sorted(keys), keys
    (run,) = {manifest["run_id"] for _, manifest in steps}
    fence = json.loads((storage / "FENCE.json").read_text())
    assert (fence["run_id"], fence["generation"], fence["attempt"]) == (run, *keys[-1]), (fence, keys)
    return [(step, manifest["attempt"]) for step, manifest in steps]
