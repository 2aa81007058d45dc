"""Set-up is idempotent and quick the second time: a stamp keyed by pyproject.toml and the torch version."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from helpers import REPO


@pytest.mark.slow  # runs launch/setup.sh
@pytest.mark.skipif(
    Path(sys.prefix).resolve() != (REPO / ".venv").resolve(),
    reason=f"runs only in the .venv that launch/setup.sh made ({REPO / '.venv'}), not in {sys.prefix}",
)
def test_a_second_setup_skips_every_install_step() -> None:
    stamps = list((REPO / ".venv").glob(".ftrain-setup-*"))
    assert len(stamps) == 1, "launch/setup.sh leaves one stamp (launch/test.sh runs it before the tests)"
    result = subprocess.run(["bash", "launch/setup.sh"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [f"setup: up to date (delete .venv/{stamps[0].name} to reinstall)"]
