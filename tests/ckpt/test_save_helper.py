"""The save helper next to each rank: idle priority, not a supervised worker, dies with its rank, survives a
SIGTERM sent to every process (as Slurm does) so that the stop save still commits."""

from __future__ import annotations

import os
import signal
import socket

import pytest
import torch

from ftrain.ckpt import handover, packing
from ftrain.ckpt.format import VERIFIED, verify_step
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.heartbeat import TOKEN_ENV
from ftrain.supervise import procfs

from helpers import REPO, assert_same, descendants, finish, kill_tree, manifests, start_train, wait_for

SCHED_IDLE = 5
LONG = ("iterations=100000", "checkpoint.interval=2")


def helpers_and_ranks(torchrun: int) -> tuple[dict[int, int], list[int]]:
    """{helper pid: its rank's pid}, and the rank pids (torchrun's children)."""
    parents = {pid: int(fields[1]) for pid in descendants(torchrun) if (fields := procfs.stat_fields(pid))}
    ranks = [pid for pid, parent in parents.items() if parent == torchrun]
    helpers = {pid: parent for pid, parent in parents.items() if parent in ranks and _is_helper(pid)}
    return helpers, ranks


def _is_helper(pid: int) -> bool:
    return b"ftrain.ckpt.helper" in procfs.read(pid, "cmdline")


def scheduling_policy(pid: int) -> int:
    return int(procfs.stat_fields(pid)[38])


@pytest.mark.slow
def test_helper_runs_at_idle_priority_unmarked_and_dies_with_its_rank(tmp_path) -> None:
    storage = tmp_path / "run"
    proc = start_train(storage, *LONG, ranks=2, env={TOKEN_ENV: "test-token"})
    try:
        wait_for(lambda: manifests(storage), "a committed checkpoint")
        helpers, ranks = helpers_and_ranks(proc.pid)
        assert len(ranks) == 2 and sorted(helpers.values()) == sorted(ranks), (helpers, ranks)
        for helper in helpers:
            assert scheduling_policy(helper) == SCHED_IDLE
            assert TOKEN_ENV.encode() not in procfs.read(helper, "environ")
        for rank in ranks:
            assert scheduling_policy(rank) == 0  # training itself keeps normal priority
        helper, rank = next(iter(helpers.items()))
        os.kill(rank, signal.SIGKILL)
        wait_for(lambda: procfs.stat_fields(helper)[:1] in ([], ["Z"]), "the helper to die", timeout=10)
    finally:
        kill_tree(proc)


@pytest.mark.slow
def test_sigterm_to_every_process_still_commits_the_stop_save(tmp_path) -> None:
    storage = tmp_path / "run"
    proc = start_train(storage, *LONG, ranks=2)
    before = max(wait_for(lambda: manifests(storage), "a committed checkpoint"))
    helpers, ranks = helpers_and_ranks(proc.pid)
    assert len(helpers) == 2
    for pid in [*ranks, *helpers]:  # what Slurm does at the end of a job step
        os.kill(pid, signal.SIGTERM)
    assert finish(proc) == 0, "the stop save must commit although its helpers were sent SIGTERM too"
    newest = max(manifests(storage))
    assert newest >= before
    assert verify_step(Storage.open(str(storage)), newest).ok


def test_a_save_travels_through_shared_memory_intact_even_when_the_slot_grows() -> None:
    """The rank's end packs into a slot far too small, so placing and then the message's pickle both grow it; the
    helper's end reads every tensor back bitwise, over the shared memory, whatever its dtype or layout."""
    weight = torch.randn(5, 7)
    states = {
        "rank-00000.pt": {
            "t": weight.t(),  # not contiguous
            "mask": torch.tensor([True, False, True]),
            "half": torch.randn(3, dtype=torch.bfloat16),
            "empty": torch.empty(0, 5, dtype=torch.float64),
            "scalar": torch.tensor(3, dtype=torch.int64),
            "note": "x" * 10_000,  # a pickle larger than the placed tensors: the slot grows with what it holds
        },
        "common.pt": {"learned": {"w": weight, "steps": torch.arange(4)}, "iteration": 7},
    }
    slot = handover.Slot(64)
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    with ours, theirs:
        handover.send(ours, ("save", handover.place(states, slot)), slot)
        (kind, files), memory = handover.receive(theirs)
    assert kind == "save" and len(slot.memory) > 10_000
    received = {name: handover.placed_tensors(packed, memory) for name, packed in files.items()}
    for name, state in states.items():
        assert_same(packing.unpack(received[name]), state)
    expected = packing.digest(packing.pack(states["common.pt"]), "learned")
    assert packing.digest(received["common.pt"], "learned") == expected
    slot.close()


def test_messages_without_a_slot_go_inline_when_small_and_through_shared_memory_when_large() -> None:
    small, large = ("committed", 4, {"metrics": {"x": 1.0}}), ("failed", 6, "y" * (2 * handover.INLINE_LIMIT))
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    with ours, theirs:
        handover.send(ours, small)
        handover.send(ours, large)
        ours.shutdown(socket.SHUT_WR)
        assert handover.receive(theirs) == (small, None)  # no shared memory for it
        message, memory = handover.receive(theirs)
        assert message == large and len(memory) >= 2 * handover.INLINE_LIMIT
        assert handover.receive(theirs) is None  # closed


def test_a_memory_run_saves_through_a_helper_thread_and_its_steps_verify(tmp_path) -> None:
    """memory:// storage lives inside one process, so the save loop runs on a thread of the rank there."""
    import uuid

    from ftrain.config import load_config
    from ftrain.train.trainer import train

    url = f"memory://ftrain-test/{uuid.uuid4().hex}"
    overrides = ["iterations=4", "checkpoint.interval=2", f"log_dir={tmp_path}", "log.console=false"]
    config = load_config(str(REPO / "configs/smoke.yaml"), overrides, storage=url)
    handlers = {number: signal.getsignal(number) for number in (signal.SIGTERM, signal.SIGINT)}
    try:
        assert train(config) == 0
    finally:
        for number, handler in handlers.items():
            signal.signal(number, handler)
    steps = scan(Storage.open(url), full=True)
    assert [(info.step, info.status) for info in steps] == [(4, VERIFIED), (2, VERIFIED)]
    assert steps[0].manifest["iteration"] == 4
