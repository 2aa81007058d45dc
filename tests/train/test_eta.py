"""The console line's ETA: smoothed over recent iterations, blind to the slow first ones after a (re)start; and which
saves the console says (a quiet console: milestones, and how long ago in the progress line)."""

from __future__ import annotations

import csv
from types import SimpleNamespace

from ftrain.train.hooks import ConsoleHook, CsvHook

from helpers import ManualClock


def estimates(durations: list[float], compute_time: float = 0.5) -> list[float]:
    """The hook's estimate after each iteration, when iterations take ``durations`` seconds of wall time."""
    clock = ManualClock()
    hook = ConsoleHook(clock)
    found = []
    for seconds in durations:
        clock.now += seconds
        found.append(hook.seconds_per_iteration(compute_time))
    return found


def test_the_slow_first_iterations_after_a_start_do_not_count() -> None:
    # a resume: imports and the first save make the first iterations 20x slower than the steady 1 s
    found = estimates([20.0, 20.0, 20.0, 1.0, 1.0, 1.0, 1.0])
    assert found[:5] == [0.5] * 5, "the compute time stands in until three steady intervals are known"
    assert found[5:] == [1.0, 1.0]


def test_a_stall_leaves_the_estimate_and_a_lasting_change_of_pace_moves_it_within_half_a_window() -> None:
    found = estimates([1.0] * 25 + [300.0] + [1.0] * 20)  # a save held 5 minutes through an outage
    assert found[24] == 1.0 and set(found[25:]) == {1.0}, "a mean would have said 16 s an iteration for 20 iterations"
    slower = estimates([1.0] * 25 + [2.0] * 20)  # the machine got busy
    assert slower[24 + 9 : 24 + 12] == [1.0, 1.5, 2.0]  # 9, 10 and 11 of the window's 20 at the new pace
    assert slower[-1] == 2.0


def saves_said(iterations: int, steps: range, every_save: bool, capsys) -> list[int]:
    """The steps whose commit the console says in a line of its own, and the progress line after the last."""
    clock = ManualClock()
    hook = ConsoleHook(clock, every_save=every_save)
    storage = SimpleNamespace(where=lambda rel: f"runs/x/{rel}")
    trainer = SimpleNamespace(
        info=SimpleNamespace(is_main=True),
        config=SimpleNamespace(iterations=iterations),
        checkpointer=SimpleNamespace(storage=storage, last_commit_s=0.1),
        iteration=0,
    )
    for step in steps:
        clock.now += 1.0
        hook.on_checkpoint(trainer, step, {"files": {"common.pt": {"size": 10}}})
    return [int(line.split()[3]) for line in capsys.readouterr().out.splitlines() if "saved step" in line]


def test_the_console_says_the_first_save_each_quarter_and_the_last_and_every_one_when_asked(capsys) -> None:
    assert saves_said(20, range(1, 21), False, capsys) == [1, 5, 10, 15, 20]  # 5 lines for 20 saves
    assert saves_said(20, range(9, 21), False, capsys) == [9, 10, 15, 20]  # a resumed process: its first, then on
    assert saves_said(20, range(1, 21), True, capsys) == list(range(1, 21))  # -v


def test_the_progress_line_says_how_long_ago_the_newest_save_was(capsys) -> None:
    clock = ManualClock()
    hook = ConsoleHook(clock)
    storage = SimpleNamespace(where=lambda rel: rel)
    trainer = SimpleNamespace(
        info=SimpleNamespace(is_main=True),
        config=SimpleNamespace(iterations=100),
        checkpointer=SimpleNamespace(storage=storage, last_commit_s=0.1),
        iteration=5,
    )
    metrics = {"iteration_time": 1.0, "mean_return": 1.0, "mean_length": 10.0, "steps_per_s": 100.0}
    metrics |= {"learning_rate": 1e-3, "loss/value": 0.5}
    hook.after_iteration(trainer, metrics)
    assert "saved" not in capsys.readouterr().out  # nothing committed yet
    hook.on_checkpoint(trainer, 5, {"files": {}})
    clock.now += 14
    hook.after_iteration(trainer, metrics)
    assert " | saved 0m14s ago | ETA " in capsys.readouterr().out.splitlines()[-1]


def test_a_metrics_file_of_an_older_version_gains_the_new_columns_and_loses_the_rows_to_redo(tmp_path) -> None:
    """A run resumed at step 2 from a metrics.csv written before the phase times and config changes existed."""
    (tmp_path / "metrics.csv").write_text("iteration,mean_return\n1,1.0\n2,2.0\n3,3.0\n")
    trainer = SimpleNamespace(
        info=SimpleNamespace(is_main=True),
        config=SimpleNamespace(log_dir=str(tmp_path)),
        checkpointer=SimpleNamespace(config_change="algorithm.gamma 0.99 -> 0.98"),
        iteration=2,
        log=print,
    )
    hook = CsvHook()
    hook.on_start(trainer)
    trainer.iteration = 3
    hook.after_iteration(trainer, {"mean_return": 3.5, "time/env_ms": 7.0})
    hook.on_end(trainer)
    with (tmp_path / "metrics.csv").open(newline="") as file:
        rows = list(csv.DictReader(file))
    assert list(rows[0]) == ["iteration", "mean_return", "time/env_ms", "resumed_from", "config_change"]
    assert [(row["iteration"], row["time/env_ms"], row["resumed_from"]) for row in rows] == [
        ("1", "", ""),
        ("2", "", ""),
        ("3", "7.0", "2"),
    ]
    assert rows[2]["config_change"] == "algorithm.gamma 0.99 -> 0.98"
