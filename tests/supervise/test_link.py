"""``--local-addr``: the address a node gives the others reaches torchrun, and the workers' gloo binds to the
interface that holds it (``tests/cluster/test_netns.py`` runs it across machines with addresses of their own)."""

from __future__ import annotations

import re

import pytest

from ftrain.ckpt.fence import GENERATION_ENV
from ftrain.config import StorageConfig
from ftrain.errors import UserError
from ftrain.supervise.auth import SECRET_ENV
from ftrain.supervise.link import rendezvous, worker_env
from ftrain.supervise.options import SupervisorOptions, parse_nodes
from ftrain.supervise.plan import Plan

ETCD = {"rdzv_backend": "etcd-v2", "rdzv_endpoint": "127.0.0.1:2379", "rdzv_id": "run"}


@pytest.mark.parametrize("backend", [ETCD, {"rdzv_endpoint": "127.0.0.1:29400"}])
def test_local_addr_goes_to_torchrun_and_its_interface_to_gloo(monkeypatch, backend, tmp_path) -> None:
    monkeypatch.delenv("GLOO_SOCKET_IFNAME", raising=False)
    monkeypatch.setenv(SECRET_ENV, "a-secret-of-sixteen-or-more")
    options = SupervisorOptions(nnodes="2:3", local_addr="127.0.0.1", **backend)
    nodes, plan = parse_nodes(options), Plan("token", 1, 29401)
    assert nodes.interface == "lo"
    assert rendezvous(plan, nodes, options)[-1] == "--local-addr=127.0.0.1"
    storage = StorageConfig(str(tmp_path / "run"))
    expected = {GENERATION_ENV: "token:1:1", "GLOO_SOCKET_IFNAME": "lo"}  # the token's epoch 1, attempt 1
    assert worker_env(plan, nodes, storage, True) == expected
    monkeypatch.setenv("GLOO_SOCKET_IFNAME", "eth7")  # the user's choice wins
    assert worker_env(plan, nodes, storage, True)["GLOO_SOCKET_IFNAME"] == "eth7"


def test_without_local_addr_the_hostname_decides_as_before(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("GLOO_SOCKET_IFNAME", raising=False)
    options = SupervisorOptions(nnodes="2:3", **ETCD)
    nodes, plan = parse_nodes(options), Plan("token", 0, None)
    assert not any(argument.startswith("--local-addr") for argument in rendezvous(plan, nodes, options))
    assert worker_env(plan, nodes, StorageConfig(str(tmp_path / "run")), False) == {GENERATION_ENV: "token:1:0"}  # etcd


def test_an_address_of_no_interface_here_is_refused() -> None:
    with pytest.raises(UserError, match=re.escape("--local-addr='198.51.100.7' is no IPv4")):
        parse_nodes(SupervisorOptions(nnodes="2:3", local_addr="198.51.100.7", **ETCD))


@pytest.mark.parametrize("backend", [ETCD, {"rdzv_endpoint": "127.0.0.1:29400"}])
@pytest.mark.parametrize(("rejoin", "left", "last_call"), [(5, None, 5), (0.2, None, 1), (5, 2, 1)])
def test_a_regroup_after_a_node_left_waits_no_rejoin_timeout(monkeypatch, backend, rejoin, left, last_call) -> None:
    """The rendezvous waits ``--rejoin-timeout`` for nodes beyond MIN (a lost node may come back), at least 1 s (torch
    refuses 0), but after a node left on its own (``Plan.left``) nobody is missing: 1 s."""
    monkeypatch.setenv(SECRET_ENV, "a-secret-of-sixteen-or-more")
    options = SupervisorOptions(nnodes="2:3", rejoin_timeout=rejoin, **backend)
    arguments = rendezvous(Plan("token", 1, 29401, left=left), parse_nodes(options), options)
    (conf,) = [argument for argument in arguments if argument.startswith("--rdzv-conf=")]
    assert f"last_call_timeout={last_call}," in conf, conf
