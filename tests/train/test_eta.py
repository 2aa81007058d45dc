"""The console line's ETA: smoothed over recent iterations, blind to the slow first ones after a (re)start."""

from __future__ import annotations

import pytest

from ftrain.train.hooks import ConsoleHook


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def estimates(durations: list[float], compute_time: float = 0.5) -> list[float]:
    """The hook's estimate after each iteration, when iterations take ``durations`` seconds of wall time."""
    clock = Clock()
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


def test_one_slow_iteration_moves_the_estimate_a_little() -> None:
    found = estimates([1.0] * 25 + [5.0, 1.0])
    assert found[24] == 1.0
    assert found[25] == pytest.approx(1.2)  # 5 s once, over a window of 20
    assert found[26] == pytest.approx(1.2)
