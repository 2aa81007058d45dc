"""``ftrain supervise``'s numeric options: a value outside its range is refused in one line that names the option, the
value and what to use, before anything starts (``SupervisorOptions`` as it is built, ``parse_nodes`` for the nodes)."""

from __future__ import annotations

import math
import re
import typing
from dataclasses import fields

import pytest

from ftrain import procfs
from ftrain.cli import main
from ftrain.errors import EXIT_USAGE, UserError
from ftrain.supervise.auth import SECRET_ENV
from ftrain.supervise.options import (
    ETCD_CONF,
    WORKER_MEMORY,
    Backend,
    Nodes,
    SupervisorOptions,
    Workers,
    parse_etcd_conf,
    parse_nodes,
    parse_workers,
)

from helpers import SMOKE

TINY = 0.001
EDGES = [  # option, a value just outside its range, a value at its edge
    ("nproc_per_node", 0, 1),
    ("nnodes", "0", "1"),
    ("node_rank", -1, 0),
    ("rdzv_timeout", 0.0, TINY),
    ("rejoin_timeout", -TINY, 0.0),
    ("max_restarts", -1, 0),  # 0: never restart
    ("hang_timeout", "0", str(TINY)),
    ("startup_grace", 0.0, TINY),
    ("backoff_initial", -TINY, 0.0),  # 0: restart at once
    ("backoff_max", -TINY, 0.0),
    ("crash_loop", -1, 0),  # 0: never stop for a crash loop
    ("storage_wait", -TINY, 0.0),  # 0: do not wait
    ("stop_grace", 0.0, TINY),
]
ETCD = {"rdzv_backend": "etcd-v2", "rdzv_endpoint": "127.0.0.1:2379", "rdzv_id": "run"}
C10D = {"rdzv_endpoint": "127.0.0.1:29400"}
HINTS = typing.get_type_hints(SupervisorOptions)


def kinds(name: str) -> set[object]:
    """An option's types: ``float | None`` is a float."""
    return {HINTS[name], *typing.get_args(HINTS[name])}


NUMERIC = [f.name for f in fields(SupervisorOptions) if {int, float} & kinds(f.name)]


def check(**values: object) -> Nodes:
    """What ``ftrain supervise`` does with its options before it launches anything: builds them, parses the nodes."""
    return parse_nodes(SupervisorOptions(**values))


def flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def test_every_numeric_option_has_its_edges_here() -> None:
    assert {name for name, _, _ in EDGES} == {*NUMERIC, "nnodes", "hang_timeout"}  # the last two: strings


@pytest.mark.parametrize(("name", "refused", "accepted"), EDGES)
def test_a_value_just_outside_its_range_is_refused_in_one_line_naming_it(name, refused, accepted) -> None:
    with pytest.raises(UserError) as error:
        check(**{name: refused})
    line = str(error.value)
    assert line.startswith(f"{flag(name)}=") and str(refused) in line and "\n" not in line, line


@pytest.mark.parametrize(("name", "refused", "accepted"), EDGES)
def test_a_value_at_the_edge_of_its_range_is_taken(name, refused, accepted) -> None:
    check(**{name: accepted})


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("name", [name for name in NUMERIC if float in kinds(name)])
def test_a_float_option_must_be_finite(name, value) -> None:
    with pytest.raises(UserError, match=f"^{flag(name)}={value} is out of range: use "):
        check(**{name: value})


def test_a_first_backoff_given_above_the_longest_is_refused_and_the_default_one_is_not() -> None:
    """``--backoff-max 0`` alone means no back-off (restarts.py waits at most --backoff-max): the default initial
    back-off must not refuse it; ``--backoff-initial 10 --backoff-max 5`` contradict each other."""
    assert SupervisorOptions(backoff_max=0.0).backoff_initial == 0.0
    assert SupervisorOptions().backoff_initial == 1.0
    check(backoff_initial=5.0, backoff_max=5.0)
    for initial, most in [(10.0, 5.0), (1.0, 0.5)]:  # given, even at its default: refused
        with pytest.raises(UserError, match=rf"^--backoff-initial={initial} is more than --backoff-max={most}: the"):
            check(backoff_initial=initial, backoff_max=most)


@pytest.mark.parametrize(
    ("nnodes", "rank", "backend", "taken"),
    [
        ("1", 0, C10D, True),
        ("1", 1, C10D, False),
        ("1", 1, ETCD, False),  # one node is node 0, whatever the backend
        ("3", 2, C10D, True),
        ("3", 3, C10D, False),
        ("2:3", 2, C10D, True),  # elastic: below MAX
        ("2:3", 3, C10D, False),
        ("3", 5, ETCD, True),  # etcd-v2's nodes: not used
    ],
)
def test_node_rank_is_below_nnodes(monkeypatch, nnodes, rank, backend, taken) -> None:
    monkeypatch.setenv(SECRET_ENV, "a-secret-of-sixteen-or-more")
    if taken:
        check(nnodes=nnodes, node_rank=rank, **backend)
        return
    with pytest.raises(UserError, match=f"^--node-rank={rank} is out of range for --nnodes={nnodes}: use 0 "):
        check(nnodes=nnodes, node_rank=rank, **backend)


@pytest.mark.parametrize(
    ("port", "taken"), [("0", False), ("65536", False), ("²", False), ("1", True), ("65535", True)]
)
def test_the_rendezvous_port_is_a_port(monkeypatch, port, taken) -> None:
    monkeypatch.setenv(SECRET_ENV, "a-secret-of-sixteen-or-more")
    if taken:
        assert check(nnodes="2", rdzv_endpoint=f"127.0.0.1:{port}").endpoint == ("127.0.0.1", int(port))
        return
    with pytest.raises(UserError, match=r"^several nodes need --rdzv-endpoint=HOST:PORT \(PORT 1 to 65535\)"):
        check(nnodes="2", rdzv_endpoint=f"127.0.0.1:{port}")


def typos(word: str) -> list[str]:
    """``word`` with each of its letters dropped, and in capitals."""
    return [*{word[:i] + word[i + 1 :] for i in range(len(word))} - {word}, word.upper()]


def test_a_misspelt_word_an_option_takes_is_told_the_one_it_is_closest_to(monkeypatch) -> None:
    """Generated cases: the words --workers, --rdzv-backend and --rdzv-conf take (checked after argparse, which only
    reads them as text), each misspelt every way ``typos`` has, are refused with the word they came from."""
    monkeypatch.setenv(SECRET_ENV, "a-secret-of-sixteen-or-more")
    etcd = {**ETCD, "nnodes": "2"}
    cases = [(typo, word, parse_workers) for word in Workers for typo in typos(word)]
    cases += [
        (typo, b.value, lambda t: check(**{**etcd, "rdzv_backend": t})) for b in Backend for typo in typos(b.value)
    ]
    cases += [(typo, key, lambda t: parse_etcd_conf(f"{t}=x")) for key in ETCD_CONF for typo in typos(key)]
    cases += [(typo, v, lambda t: parse_etcd_conf(f"protocol={t}")) for v in ETCD_CONF["protocol"] for typo in typos(v)]
    checked = 0
    for typo, meant, parse in cases:
        if typo in ("http", "https"):  # https less its s: the other word, taken
            continue
        with pytest.raises(UserError) as refused:
            parse(typo)
        assert f"(did you mean {meant}?)" in str(refused.value), (typo, str(refused.value))
        checked += 1
    with pytest.raises(UserError, match=r"'protocl' is not an etcd connection setting .*\(did you mean protocol\?\)"):
        check(rdzv_backend="etcd-v2", rdzv_conf="protocl=http")  # one node: no use for it, but a typo is told
    print(f"{checked} misspelt option words told the one they came from")
    assert checked > 70


def test_the_command_refuses_it_in_one_line_before_it_starts_anything(monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.delenv("RANK", raising=False)
    monkeypatch.delenv("TORCHELASTIC_ERROR_FILE", raising=False)
    storage = tmp_path / "run"
    assert main(["supervise", "--startup-grace", "-1", "configs/smoke.yaml", "--storage", str(storage)]) == EXIT_USAGE
    said = "--startup-grace=-1.0 is out of range: use a positive number of seconds, e.g. 300"
    assert capsys.readouterr().err == f"ftrain: error: {said}\n"
    assert not storage.exists()


def test_more_workers_than_the_memory_holds_are_refused_with_a_number_that_fits(tmp_path, capsys) -> None:
    """A probe's ``--nproc-per-node 5000`` on a 2-core machine started 430 processes and took 7 GB in 20 s before
    anything could say no. Now ``--nproc-per-node`` is weighed against the memory available at the start: refused in
    one line with a value that fits (taken), nothing started, nothing written."""
    too_many = 2 * procfs.available_memory() // WORKER_MEMORY
    with pytest.raises(UserError, match=rf"^--nproc-per-node={too_many}: that many workers need at least ") as error:
        check(nproc_per_node=too_many)
    suggested = int(re.search(r"use --nproc-per-node=(\d+) or fewer$", str(error.value))[1])
    assert too_many // 3 < suggested < too_many * 2 // 3  # half of it, as the memory available moves between looks
    check(nproc_per_node=suggested // 2)  # other tests beside this one take and free gigabytes
    storage = tmp_path / "run"
    assert main(["supervise", f"--nproc-per-node={too_many}", SMOKE, "--storage", str(storage)]) == EXIT_USAGE
    assert capsys.readouterr().err.startswith(f"ftrain: error: --nproc-per-node={too_many}: that many workers")
    assert not storage.exists()


@pytest.mark.parametrize("value", ["inf", "1e400", "Infinity", "nan", "-5", "abc"])
def test_a_hang_timeout_that_would_never_catch_a_hang_is_refused(value) -> None:
    """A probe's ``--hang-timeout inf`` (and ``1e400``, which float reads as inf) turned hang detection off without a
    word, where 0 and nan were refused."""
    with pytest.raises(UserError, match=rf"^--hang-timeout='{value}' must be auto or a positive number of seconds$"):
        check(hang_timeout=value)
