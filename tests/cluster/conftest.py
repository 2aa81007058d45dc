"""The private SLURM cluster of ``slurm_cluster.py``: three nodes, started once for this directory's tests (they
skip, with the reason, where it cannot run), and after each test every job gone and every node back in service; and
simulated machines in network namespaces (``netns.py``), made anew for each test that asks for them."""

from __future__ import annotations

import shutil

import pytest

import etcd_server as etcd_tools
import netns
from slurm_cluster import SlurmCluster, missing


@pytest.fixture(scope="session")
def private_slurm():
    if reason := missing():
        pytest.skip(reason)
    cluster = SlurmCluster(nodes=3)
    try:
        cluster.start()
        yield cluster
    finally:
        cluster.stop()


@pytest.fixture
def slurm(private_slurm: SlurmCluster):
    yield private_slurm
    private_slurm.cancel_all()
    for node in private_slurm.down():
        private_slurm.start_node(node)
    private_slurm.wait(lambda: private_slurm.idle() == set(private_slurm.nodes), "every node idle", timeout=120)


@pytest.fixture
def network(request, tmp_path):
    """Four simulated machines (``netns.Bed``): hosts 0-2 for the nodes, host 3 for etcd, which runs there on its own
    address; yields ``(bed, etcd's client address)``. Parametrized indirectly with a number: that many milliseconds
    of latency on every link. Skips where namespaces cannot be made or etcd is missing; every
    namespace and what runs in it goes at the end, whatever happened."""
    if reason := netns.missing() or (None if shutil.which("etcd") else etcd_tools.MISSING):
        pytest.skip(reason)
    bed = netns.Bed(4)
    try:
        bed.start(getattr(request, "param", 0))
        with etcd_tools.etcd_server(tmp_path, host=bed.address(3), launcher=bed.launcher(3)) as endpoint:
            yield bed, endpoint
    finally:
        bed.stop()
