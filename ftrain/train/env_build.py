"""Building a rank's environments, the one step of a start whose time and memory grow with the input
(``env.num_envs``, and the ranks on one machine): a build that would not fit in the memory the machine has left is
refused after its first environments, before it takes the machine down; a long one says how long it will take. The
ranks then agree (``agree``), so that every rank refuses alike, not one while the others wait for it. (A stop while
it builds ends the process at once: ``ftrain.train.stop``.)

May import: the standard library, ``ftrain.errors``, ``ftrain.procfs``, ``ftrain.comm.group``.
"""

from __future__ import annotations

import time
import typing

from ftrain import procfs
from ftrain.comm import group
from ftrain.errors import UserError

SAMPLE = 16
"""Environments built (after the first, which loads the model) before the memory and time of one are measured."""
SHARE = 0.8
"""Of the memory available at the start, what the environments may take: the rest is for the model, the rollout
buffers and the evaluation's environments."""
SAY_AFTER_S = 10.0
SAY_FROM = 1000
"""A build expected to take over ``SAY_AFTER_S`` seconds, or of ``SAY_FROM`` environments or more, says so, once."""


class TooLarge(Exception):
    """The environments would not fit in memory: the message says so, with a value that fits."""


class BuildWatch:
    """Called with the number built after each environment (``MujocoVecEnv``'s ``built``); raises ``TooLarge``.

    ``total``: the environments of this rank; ``setting``: the config key and value the user gave for them
    (``env.num_envs=200000``, or ``env.total_envs``, shared by the ranks); ``ranks_here``: the ranks building on this
    machine at once."""

    def __init__(
        self,
        total: int,
        setting: tuple[str, int],
        ranks_here: int,
        log: typing.Callable[[str], None],
    ) -> None:
        self.total, self.setting, self.ranks_here, self.log = total, setting, ranks_here, log
        self._after_first: tuple[int, float] = (0, 0.0)

    def __call__(self, built: int) -> None:
        if built == 1:
            self._after_first = (procfs.resident_bytes(), time.perf_counter())
        elif built == 1 + SAMPLE and built < self.total:
            memory, started = self._after_first
            per_env = max(procfs.resident_bytes() - memory, 0) / SAMPLE
            self._check_memory(per_env, procfs.available_memory())
            seconds = (time.perf_counter() - started) / SAMPLE * (self.total - built)
            if seconds > SAY_AFTER_S or self.total >= SAY_FROM:
                self.log(f"building {self.total:,} environments per rank: about {seconds:.0f} s")

    def _check_memory(self, per_env: float, available: int | None) -> None:
        need = per_env * self.total * self.ranks_here
        if available is None or need <= SHARE * available:
            return
        name, value = self.setting
        fits = int(SHARE * available / (per_env * self.ranks_here) * value / self.total)
        ranks = f"{self.ranks_here} ranks on this machine" if self.ranks_here > 1 else "1 rank"
        raise TooLarge(
            f"{name}={value}: its environments need about {_gb(need)} of memory ({per_env / 1e6:.1f} MB each, "
            f"{ranks}), and this machine has {_gb(available)} available: use {name}={max(fits, 1)} or fewer"
        )


def agree(refused: TooLarge | None, info: group.RankInfo) -> None:
    """Every rank, after its build: UserError if any rank's build was refused."""
    if refusal := next(filter(None, group.all_gather_object(refused and str(refused), info)), None):
        raise UserError(refusal)


def _gb(size: float) -> str:
    return f"{size / 1e9:.1f} GB"
