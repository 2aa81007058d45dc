"""Where an iteration's time goes: every second in exactly one phase, a nested phase pausing the one it interrupts."""

from __future__ import annotations

import pytest

from ftrain.train.phases import PHASES, Phases

from helpers import ManualClock


def test_nested_phases_pause_the_outer_one_and_the_rest_is_other() -> None:
    clock = ManualClock()
    phases = Phases(clock)
    clock.now = 1.0  # outside every phase
    with phases("update"):
        clock.now = 3.0
        with phases("sync_update"):
            clock.now = 3.5
        clock.now = 6.0
    with phases("env"):
        clock.now = 6.25
    taken = phases.take()
    assert taken == {**dict.fromkeys(PHASES, 0.0), "other": 1.0, "update": 4.5, "sync_update": 0.5, "env": 0.25}
    assert sum(taken.values()) == clock.now


def test_a_take_counts_afresh_and_a_phase_open_across_it_is_split() -> None:
    clock = ManualClock()
    phases = Phases(clock)
    with phases("sync_metrics"):
        clock.now = 2.0
        assert phases.take()["sync_metrics"] == 2.0
        clock.now = 2.5
    clock.now = 4.0
    taken = phases.take()
    assert (taken["sync_metrics"], taken["other"], sum(taken.values())) == (0.5, 1.5, 2.0)


def test_an_unknown_phase_is_refused_before_it_is_entered() -> None:
    clock = ManualClock()
    phases = Phases(clock)
    with pytest.raises(KeyError, match="rendering"):
        phases("rendering")
    with phases("env"):
        clock.now = 1.0
    assert phases.take()["env"] == 1.0
