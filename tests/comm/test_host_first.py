"""Host-first collectives on real torchrun nodes: each node a torchrun agent of its own on this machine, its ranks
sharing memory, the nodes meeting through gloo."""

from __future__ import annotations

import json
import socket
import subprocess
import sys

import pytest

from helpers import REPO, SMOKE, child_env, final_manifest, metrics_by_iteration, run_train

TIMEOUT = 5.0
"""The collectives' timeout in these runs: a dead peer must end the others within it."""


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def start_nodes(per_node: list[int], command: list[str], tmp_path, env: dict | None = None) -> list[subprocess.Popen]:
    """One torchrun agent per entry of ``per_node`` (its ranks), joined by c10d's rendezvous on 127.0.0.1."""
    port, nodes = free_port(), []
    for node, ranks in enumerate(per_node):
        rendezvous = [f"--nnodes={len(per_node)}", f"--nproc-per-node={ranks}", "--rdzv-backend=c10d"]
        rendezvous += [f"--rdzv-endpoint=127.0.0.1:{port}", f"--rdzv-conf=is_host={int(node == 0)}"]
        launcher = [sys.executable, "-m", "torch.distributed.run", *rendezvous]
        log = open(tmp_path / f"node{node}.log", "w")  # noqa: SIM115 - the agent writes to it until it ends
        nodes.append(subprocess.Popen([*launcher, *command], cwd=REPO, env=child_env(env), stdout=log, stderr=log))
    return nodes


@pytest.mark.slow  # ranks under torchrun
@pytest.mark.parametrize("per_node", [[2, 2], [1, 2], [2, 1, 1]], ids=["2+2", "1+2", "2+1+1"])
def test_host_first_collectives_hand_on_every_bit_and_a_dead_peer_ends_the_others(tmp_path, per_node) -> None:
    """Gathers and broadcasts give gloo's own bits; the small float64 sums are the rank-ordered sum of what every rank
    sent, as on one host; the all-reduce is gloo's to rounding and the same bits on every rank. Then the last rank
    dies between two collectives: a survivor on its host sees its shared memory's peer gone, the others gloo's, all
    within the timeout."""
    out, ranks = tmp_path / "report.json", sum(per_node)
    worker = [str(REPO / "tests" / "comm" / "host_first_worker.py"), str(out), str(TIMEOUT)]
    nodes = start_nodes(per_node, worker, tmp_path)
    for node in nodes:
        node.wait(timeout=120)
    logs = "\n".join(path.read_text()[-1500:] for path in sorted(tmp_path.glob("node*.log")))
    reports = {}
    for rank in range(ranks - 1):  # the last rank dies once the collectives are checked
        report = out.with_name(f"{out.name}.{rank}")
        assert report.exists(), f"rank {rank} wrote no report:\n{logs}"
        reports[rank] = json.loads(report.read_text())
    for layout in ("torchrun", "interleaved"):
        assert len({report[layout]["digest"] for report in reports.values()}) == 1, f"{layout}: the same bits on all"
    for rank, report in reports.items():
        assert report["kind"] == "HostFirst" and len(set(report["hosts"])) == len(per_node), report["hosts"]
        assert report["disagreeing_hosts"] is None, "hosts that disagree with torchrun's count: no memory shared"
        for layout in ("torchrun", "interleaved"):
            checks = report[layout]
            assert checks["gathers"] and checks["broadcasts"], f"rank {rank}, {layout}: every bit handed on"
            assert checks["sums"], f"rank {rank}, {layout}: the small sums in rank order, bit for bit"
            assert checks["reduced"], f"rank {rank}, {layout}: the all-reduce equals gloo's to rounding"
        assert report["peer_lost"], f"rank {rank}: a collective with a dead peer must fail"
        assert report["seconds"] < TIMEOUT + 5, f"rank {rank}: noticed only after {report['seconds']:.1f} s"


@pytest.mark.slow  # two trainings of 4 ranks
@pytest.mark.parametrize("split", [True, False], ids=["split", "data-parallel"])
def test_two_hosts_train_what_one_host_trains(tmp_path, split: bool) -> None:
    """4 ranks as 2 nodes x 2 (the split update's teams each on its own node, meeting host first) learn the same
    bits as 4 ranks on one node, every metric included: a gather and a broadcast hand on every bit, and the
    iteration's small sums (the reward normaliser's statistics among them) add the same numbers in the same order.
    Data-parallel, the gradients are summed within each node and then across, (a + b) + (c + d) where one node sums
    ((a + b) + c) + d: the same learning to rounding."""
    overrides = ["reward.normalize=true", "iterations=4", "log.console=false", f"split_update={str(split).lower()}"]
    run_train(tmp_path / "one", *overrides, ranks=4, supervised=True)  # warm workers: one import, not four
    train = ["-m", "ftrain", "train", SMOKE, "--storage", str(tmp_path / "two"), *overrides]
    nodes = start_nodes([2, 2], train, tmp_path)
    codes = [node.wait(timeout=300) for node in nodes]
    assert codes == [0, 0], "\n".join(path.read_text()[-2000:] for path in sorted(tmp_path.glob("node*.log")))
    one, two = (metrics_by_iteration(tmp_path / name) for name in ("one", "two"))
    assert one.keys() == two.keys() == {1, 2, 3, 4}
    if split:
        assert final_manifest(tmp_path / "two")["state_sha256"] == final_manifest(tmp_path / "one")["state_sha256"]
        assert two == one, "every metric but the clocks, the same at every iteration"
    for iteration in (1, 2):  # (rounding grows as training goes on: 1e-6 after the second update, 1e-3 after the third)
        ours, theirs = ({key: float(value) for key, value in row[iteration].items() if value} for row in (two, one))
        assert ours == pytest.approx(theirs, rel=1e-4, abs=1e-6, nan_ok=True), f"iteration {iteration}"
