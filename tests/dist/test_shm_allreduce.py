"""The shared-memory all-reduce between ranks of one host, on 2 real torchrun ranks."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from helpers import REPO, child_env


@pytest.mark.slow  # ranks under torchrun
def test_shared_memory_all_reduce_is_exact_leaves_nothing_and_notices_a_dead_peer(tmp_path) -> None:
    out = tmp_path / "report.json"
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2"]
    subprocess.run(
        [*launcher, str(REPO / "tests" / "dist" / "shm_worker.py"), str(out)],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        timeout=120,
    )
    report = json.loads(out.read_text())
    assert report["exact"], "the shared-memory sum must equal gloo's bit for bit"
    assert report["leftovers"] == [], "segment and pipes must be unlinked once every rank has opened them"
    assert report["peer_lost"] == "a peer rank exited during an all-reduce"
    assert report["seconds"] < 15, "a dead peer must be noticed at once, not after the 30 s timeout"
