"""The private SLURM cluster of ``slurm_cluster.py``: three nodes, started once for this directory's tests (they
skip, with the reason, where it cannot run), and after each test every job gone and every node back in service."""

from __future__ import annotations

import pytest

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
