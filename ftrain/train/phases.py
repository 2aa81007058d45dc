"""Where an iteration's wall time goes on one rank, phase by phase: the measurement that scaling work starts from.

A rank is always in exactly one phase: entering one pauses the phase it was in (the update's compute pauses while
its all-reduce runs), and whatever runs outside every named phase counts as ``other`` (hooks, heartbeats, the
checkpoint, the learning-rate schedule). So the phases of a row add up to the wall time since the row before. The
trainer gathers every rank's phases in the iteration's metrics collective, which it already makes, and
``metrics.csv`` gets, in milliseconds, the mean over ranks, ``time/<phase>_ms``, and the slowest rank's,
``time/<phase>_max_ms`` (where the ranks' work differs, as in a split update, the mean hides which one paces the
others). That collective itself, and what follows it (the save, if any), count in the next row.

A rank that waits inside a collective is paced by a slower peer: a large ``sync`` time next to a compute time that
the slowest rank needs beside it is the sign of imbalance, not of a slow network.
"""

from __future__ import annotations

import time
from collections.abc import Callable

PHASES = ("env", "policy", "buffer", "sync_rewards", "update", "sync_update", "sync_metrics", "other")
"""``env``: MuJoCo stepping and observations; ``policy``: the actor and critic on each step's observations;
``buffer``: storing transitions, reward normalisation, returns and advantages; ``sync_rewards``: inside the
all-reduce of the reward normaliser's statistics after the rollout, where the ranks first wait for each other;
``update``: the update's compute
(forward, backward, optimizer); ``sync_update``: inside the update's all-reduces (gradients, observation statistics),
waiting for peers included; ``sync_metrics``: inside the iteration's metrics and votes all-reduce; ``other``: the
rest."""


class Phases:
    """This rank's seconds per phase since the last :meth:`take`. Use as ``with phases("env"): ...``."""

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self._clock = clock
        self._current = "other"
        self._mark = clock()
        self.seconds = dict.fromkeys(PHASES, 0.0)

    def __call__(self, name: str) -> _Phase:
        if name not in self.seconds:
            raise KeyError(f"no phase {name!r}: one of {', '.join(PHASES)}")
        return _Phase(self, name)

    def switch(self, name: str) -> str:
        """Charge the time since the last switch to the current phase and enter ``name``; the phase left."""
        now = self._clock()
        self.seconds[self._current] += now - self._mark
        self._mark = now
        left, self._current = self._current, name
        return left

    def take(self) -> dict[str, float]:
        """Seconds per phase since the last take (the current phase up to now), and start counting afresh."""
        self.switch(self._current)
        taken, self.seconds = self.seconds, dict.fromkeys(PHASES, 0.0)
        return taken


class _Phase:
    """One ``with`` block of a phase: back to the phase it interrupted when it ends."""

    __slots__ = ("_left", "_name", "_phases")

    def __init__(self, phases: Phases, name: str) -> None:
        self._phases, self._name, self._left = phases, name, "other"

    def __enter__(self) -> None:
        self._left = self._phases.switch(self._name)

    def __exit__(self, *exc: object) -> None:
        self._phases.switch(self._left)
