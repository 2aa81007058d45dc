"""Which rank the supervisor blames, from error files written the way workers write them."""

from __future__ import annotations

import json
import signal

import pytest

from ftrain import errorfile
from ftrain.errors import EXIT_STORAGE_DOWN, EXIT_USAGE
from ftrain.supervise.outcome import WorkerFailure, blame, classify


def recorded(tmp_path, monkeypatch, rank: int, code: int, error: BaseException | None) -> WorkerFailure:
    """How torchrun passes on a failed worker: its exit code and the JSON of its error file (if it wrote one)."""
    path = tmp_path / f"error-{rank}.json"
    monkeypatch.setenv(errorfile.ENV, str(path))
    if error is not None:
        try:
            raise error
        except type(error) as caught:
            errorfile.record_exception(caught)
    data = json.loads(path.read_text()) if path.exists() else None
    return WorkerFailure(code, errorfile.message(data), errorfile.recorded_at(data))


def test_the_rank_that_raised_first_is_blamed_not_the_peer_that_failed_after_it(tmp_path, monkeypatch) -> None:
    """Seen under load: rank 1 raises; rank 0 records the broken all-reduce, then torchrun's SIGTERM ends it."""
    cause = recorded(tmp_path, monkeypatch, 1, 1, RuntimeError("probe crash"))
    after = recorded(tmp_path, monkeypatch, 0, -signal.SIGTERM, RuntimeError("a peer rank exited during an all-reduce"))
    assert after.recorded_at > cause.recorded_at
    assert blame({0: after, 1: cause}, killed=set()) == (1, cause)
    later_exit = WorkerFailure(1, after.error, after.recorded_at)  # the same, had rank 0 exited on its own
    assert blame({0: later_exit, 1: cause}, killed=set()) == (1, cause)


def test_a_rank_killed_by_a_signal_is_blamed_before_ranks_that_failed_on_the_broken_group(
    tmp_path, monkeypatch
) -> None:
    broken = recorded(tmp_path, monkeypatch, 0, 1, RuntimeError("Connection reset by peer"))
    killed = recorded(tmp_path, monkeypatch, 1, -signal.SIGKILL, None)
    assert killed.error is None and killed.recorded_at == float("inf")
    assert blame({0: broken, 1: killed}, killed=set()) == (1, killed)


def test_ranks_the_supervisor_killed_are_not_blamed_and_without_records_a_specific_code_wins(tmp_path) -> None:
    sigkilled = WorkerFailure(-signal.SIGKILL, None)
    assert blame({0: sigkilled, 1: WorkerFailure(1, None)}, killed={0}) == (1, WorkerFailure(1, None))
    terminated, specific = WorkerFailure(-signal.SIGTERM, None), WorkerFailure(3, None)
    assert blame({0: terminated, 1: WorkerFailure(1, None), 2: specific}, killed=set()) == (2, specific)
    assert blame({}, killed=set()) is None


def test_a_refusal_is_blamed_even_when_another_rank_recorded_first_and_torchrun_stopped_it(tmp_path) -> None:
    """Seen under load: rank 1 recorded the same refusal first, then torchrun's SIGTERM ended it before it exited 2."""
    refused = WorkerFailure(EXIT_USAGE, "checkpoint step 2 ... refused", recorded_at=2.0)
    stopped = WorkerFailure(-signal.SIGTERM, "checkpoint step 2 ... refused", recorded_at=1.0)
    assert blame({0: refused, 1: stopped}, killed=set()) == (0, refused)


def test_a_rank_that_could_not_reach_the_storage_is_blamed_after_a_refusal_and_before_any_crash(tmp_path) -> None:
    """The storage is down: rank 0 exits 7; rank 1, waiting in a collective, fails on the broken group first."""
    unreachable = WorkerFailure(EXIT_STORAGE_DOWN, "cannot reach the S3 endpoint ...", recorded_at=2.0)
    broken = WorkerFailure(1, "RuntimeError: Connection reset by peer", recorded_at=1.0)
    killed = WorkerFailure(-signal.SIGKILL, None)
    assert blame({0: unreachable, 1: broken, 2: killed}, killed=set()) == (0, unreachable)
    refused = WorkerFailure(EXIT_USAGE, "bad input", recorded_at=3.0)
    assert blame({0: unreachable, 1: refused}, killed=set()) == (1, refused)
    outcome = classify(1, "", (0, unreachable), None, False, {"start"}, False, None)
    assert outcome.event == "storage_down" and outcome.failed and outcome.code is None


@pytest.mark.parametrize(("superseded", "event", "code"), [(False, "preempted", 143), (True, "failed", None)])
def test_workers_that_saved_and_stopped_unasked_are_preempted_unless_another_node_ended_the_attempt(
    superseded, event, code
):
    """torchrun exits 143, every worker saved, and nobody signalled this supervisor: stopped from outside (preempted),
    unless another node ended the attempt (it failed, or its torchrun restarted every rank's workers for a node that
    joined late, before this node's torchrun saw the new node): then a restart."""
    outcome = classify(143, "rank 0 exited with code 143", None, None, False, {"preempted"}, superseded, 40)
    assert (outcome.event, outcome.code) == (event, code), outcome


@pytest.mark.parametrize(("committed", "words"), [(None, "no step committed yet"), (40, "newest step 40")])
def test_an_ending_names_the_newest_step_in_words_also_when_there_is_none(committed, words) -> None:
    """A stop before the first commit said "newest step None"."""
    for code, stopped, phases in ((143, 143, {"rollout"}), (143, None, {"preempted"}), (6, None, set())):
        outcome = classify(code, "", None, stopped, False, phases, False, committed)
        assert f"({words})" in outcome.message and "None" not in outcome.message, outcome


@pytest.mark.parametrize("code", [0, 1, -9, 143])
@pytest.mark.parametrize("stopped", [None, 143])
def test_every_worker_done_is_finished_whatever_torchrun_exits_with(code, stopped) -> None:
    """Every worker beat ``done`` (the last step committed): the run finished, whether torchrun then exited 0, failed
    in its own exit, was killed (stopped under its workers, ``Supervisor._torchrun_stopped``), or got the stop;
    workers that outlived torchrun, or one not done, keep the attempt's own outcome."""
    outcome = classify(code, "torchrun killed by SIGKILL", None, stopped, False, {"done"}, False, 40)
    assert (outcome.event, outcome.code, outcome.failed) == ("done", 0, False), outcome
    for orphans, phases in ((True, {"done"}), (False, {"done", "rollout"})):
        other = classify(code, "", None, stopped, orphans, phases, False, 40)
        assert other.event != "done" or (code == 0 and stopped is None and not orphans), other
