"""``--local-addr``: the address a node gives the others reaches torchrun, and the workers' gloo binds to the
interface that holds it (``tests/cluster/test_netns.py`` runs it across machines with addresses of their own)."""

from __future__ import annotations

import json
import re
import threading

import pytest

from ftrain.ckpt.lease import LEASE, Lease, Record
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError
from ftrain.identity import ATTEMPT_ENV, GENERATION_ENV, RUN_ID_ENV
from ftrain.procfs import Process
from ftrain.supervise.auth import SECRET_ENV
from ftrain.supervise.etcd_plan import EtcdLink
from ftrain.supervise.link import rendezvous, worker_env
from ftrain.supervise.options import SupervisorOptions, parse_nodes
from ftrain.supervise.plan import Plan

ETCD = {"rdzv_backend": "etcd-v2", "rdzv_endpoint": "127.0.0.1:2379", "rdzv_id": "run"}


@pytest.mark.parametrize("backend", [ETCD, {"rdzv_endpoint": "127.0.0.1:29400"}])
def test_local_addr_goes_to_torchrun_and_its_interface_to_gloo(monkeypatch, backend, tmp_path) -> None:
    monkeypatch.delenv("GLOO_SOCKET_IFNAME", raising=False)
    monkeypatch.setenv(SECRET_ENV, "a-secret-of-sixteen-or-more")
    options = SupervisorOptions(nnodes="2:3", local_addr="127.0.0.1", **backend)
    nodes, plan = parse_nodes(options), Plan(3, 1, 29401)
    assert nodes.interface == "lo"
    assert rendezvous(plan, nodes, options)[-1] == "--local-addr=127.0.0.1"
    expected = {RUN_ID_ENV: "run-a", GENERATION_ENV: "3", ATTEMPT_ENV: "1", "GLOO_SOCKET_IFNAME": "lo"}
    assert worker_env(plan, nodes, "run-a") == expected
    monkeypatch.setenv("GLOO_SOCKET_IFNAME", "eth7")  # the user's choice wins
    assert worker_env(plan, nodes, "run-a")["GLOO_SOCKET_IFNAME"] == "eth7"


def test_without_local_addr_the_hostname_decides_as_before(monkeypatch, tmp_path) -> None:
    monkeypatch.delenv("GLOO_SOCKET_IFNAME", raising=False)
    options = SupervisorOptions(nnodes="2:3", **ETCD)
    nodes, plan = parse_nodes(options), Plan(1, 0, None)
    assert not any(argument.startswith("--local-addr") for argument in rendezvous(plan, nodes, options))
    assert worker_env(plan, nodes, "run-a") == {RUN_ID_ENV: "run-a", GENERATION_ENV: "1", ATTEMPT_ENV: "0"}  # etcd


def test_one_node_alone_hands_its_workers_no_attempt(tmp_path) -> None:
    """One node runs one attempt at a time: its workers' commits are checked against the lease only."""
    nodes = parse_nodes(SupervisorOptions())
    assert worker_env(Plan(2, 5, None), nodes, "run-a") == {RUN_ID_ENV: "run-a", GENERATION_ENV: "2", ATTEMPT_ENV: ""}


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
    arguments = rendezvous(Plan(1, 1, 29401, left=left), parse_nodes(options), options)
    (conf,) = [argument for argument in arguments if argument.startswith("--rdzv-conf=")]
    settings = dict(setting.split("=") for setting in conf.removeprefix("--rdzv-conf=").split(","))
    assert settings["last_call_timeout"] == str(last_call), conf


@pytest.mark.cluster
def test_on_etcd_nodes_starting_at_once_make_one_plan_at_one_new_generation(tmp_path, etcd_server) -> None:
    """Three nodes of a run start at once on etcd and find no plan: the one that took the next generation of the
    storage's lease makes the plan at it, the others, which joined it, follow it (no plan is made twice, which would
    stop the first one's workers). The same command after the run's end makes a new plan at the next generation."""
    storage = Storage.open(str(tmp_path / "run"))
    options = SupervisorOptions(nnodes="3", rdzv_backend="etcd-v2", rdzv_endpoint=etcd_server, rdzv_id="job")
    nodes = parse_nodes(options)
    storage.write_replace(LEASE, Record("job", 4, 60.0, ()).encode())  # the run's last start ended at generation 4
    old = {"token": "an older ftrain's", "attempt": 3, "port": None, "final": None, "left": None}
    EtcdLink(nodes, timeout=10).client.write("/ftrain/job/plan", json.dumps(old))  # not a plan this ftrain reads

    def leases() -> list[Lease]:  # the nodes of a start of the run, on three hosts: each renews its own entry
        started = [Lease(storage, "job", print, follows=True) for _ in range(3)]
        for number, lease in enumerate(started):
            lease.process = Process(f"host-{number}", 100 + number, 1, "boot", "pid:[1]")
            lease.acquire()
        return started

    def begin(started: list[Lease]) -> list[EtcdLink]:
        links = [EtcdLink(nodes, timeout=10) for _ in started]
        pairs = zip(links, started, strict=True)
        threads = [threading.Thread(target=link.begin, args=(lease,)) for link, lease in pairs]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(timeout=60)
        return links

    first = leases()
    assert [lease.took for lease in first] == [True, False, False]  # one new holder; the others joined it
    links = begin(first)
    assert [link.generation for link in links] == [5, 5, 5]
    plan = links[0].ask("plan")
    assert (plan.generation, plan.attempt, plan.final) == (5, 0, None) and plan.nonce
    links[0].ask("finish", code=0)
    for lease in first:
        lease.release()
    again = begin(leases())  # the same command after the run's end: the next generation, another rendezvous id
    assert [link.generation for link in again] == [6, 6, 6] and again[0].ask("plan").nonce != plan.nonce
