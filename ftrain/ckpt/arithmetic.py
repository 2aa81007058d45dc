"""A rank's arithmetic: what decides the bits it computes besides the code, the config and the seed.

torch's matrix products go through MKL, whose code path follows the CPU (its vendor and instruction set, unless
``MKL_CBWR`` pins one), and ATen's vector kernels follow the instruction set (unless ``ATEN_CPU_CAPABILITY`` pins
one); torch, MuJoCo and numpy compute the rest. Two ranks of one arithmetic compute the same bits from the same
state; on another, a run trains the same way but other bits, so its curve parts from the first after a few
iterations. Each manifest records every rank's (``by_rank``), and a resume on another says so in one line
(``change``): a run moved to another CPU type continues, not bit for bit (docs/checkpoints.md).

Imports: the standard library and torch only.
"""

from __future__ import annotations

import importlib.metadata
import os
import platform
from pathlib import Path

import torch

PINS = ("MKL_CBWR", "ATEN_CPU_CAPABILITY")
"""The environment variables that choose a code path where the CPU would."""
PACKAGES = ("torch", "mujoco", "numpy")


def describe() -> str:
    """This process's arithmetic in one line, e.g. ``AMD EPYC, AVX512 kernels; torch 2.13.0+cpu, mujoco 4.0.0, ...``."""
    kernels = f"{_cpu()}, {torch.backends.cpu.get_cpu_capability()} kernels"
    pins = [f"{name}={os.environ[name]}" for name in PINS if os.environ.get(name)]
    installed = ", ".join(f"{package} {version or 'none'}" for package, version in versions(PACKAGES).items())
    return "; ".join([kernels, *pins, installed])


def by_rank(descriptions: list[str]) -> dict[str, list[int]]:
    """Every rank's ``describe()`` (in rank order) as the manifest keeps it: each arithmetic with its ranks."""
    ranks: dict[str, list[int]] = {}
    for rank, description in enumerate(descriptions):
        ranks.setdefault(description, []).append(rank)
    return ranks


def change(saved: dict[str, list[int]] | None, descriptions: list[str]) -> str | None:
    """How the ranks' arithmetic differs from a manifest's (``by_rank``) where both have the rank, in words; None:
    not at all, or not recorded (a manifest of an older ftrain)."""
    if not saved:
        return None
    before = {rank: description for description, ranks in saved.items() for rank in ranks}
    moved = [rank for rank, now in enumerate(descriptions) if rank in before and before[rank] != now]
    if not moved:
        return None
    first = moved[0]
    ranks = "rank" if len(moved) == 1 else "ranks"
    return f"{ranks} {', '.join(map(str, moved))}: {descriptions[first]} (was {before[first]})"


def _cpu() -> str:
    """The CPU's model name, as Linux reports it (``platform.processor()`` elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.partition(":")[2].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def versions(packages: tuple[str, ...]) -> dict[str, str | None]:
    """Each installed package's version (None: not installed); the manifests' ``versions`` too."""
    found: dict[str, str | None] = {}
    for package in packages:
        try:
            found[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            found[package] = None
    return found
