"""How fast this machine is today, in the unit the test suite spends: the CPU and wall seconds of one cold
``ftrain train configs/smoke.yaml iterations=2`` (a Python start, the imports of torch, MuJoCo and rsl-rl, two tiny
iterations, a checkpoint). These machines differ 2-3x from day to day, so a suite's wall time means little alone:
``launch/test.sh`` prints this line first, and two suites compare by their minutes per smoke CPU-second.

    .venv/bin/python launch/machine_speed.py
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def cold_smoke() -> tuple[float, float]:
    """CPU and wall seconds of one cold 2-iteration smoke run, in a directory of its own."""
    with tempfile.TemporaryDirectory(prefix="ftrain-speed-") as scratch:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        began = time.monotonic()
        subprocess.run(
            [sys.executable, "-m", "ftrain", "train", str(REPO / "configs/smoke.yaml"), "iterations=2"],
            cwd=scratch,
            check=True,
            stdout=subprocess.DEVNULL,
            env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
        )
        wall = time.monotonic() - began
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime, wall


if __name__ == "__main__":
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()  # --help says what it does; no options
    try:
        cpu, wall = cold_smoke()
    except subprocess.CalledProcessError as error:  # a line, not the end of the test run that prints it first
        print(f"machine speed: not measured (the smoke run exited {error.returncode})")
    else:
        cores = os.cpu_count()
        print(f"machine speed: a cold 2-iteration smoke run took {cpu:.1f} CPU-s ({wall:.1f} s wall) on {cores} cores")
