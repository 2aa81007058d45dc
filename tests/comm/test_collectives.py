"""Object collectives between real ranks carry JSON: data round-trips, objects are refused, pickles never run."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import REPO, child_env

WORKER = REPO / "tests" / "comm" / "collectives_worker.py"


@pytest.mark.slow  # ranks under torchrun
def test_objects_travel_as_json_and_a_peer_cannot_send_code(tmp_path) -> None:
    marker = tmp_path / "code-ran"
    out = tmp_path / "report"
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2"]
    subprocess.run([*launcher, str(WORKER), str(out), str(marker)], cwd=REPO, env=child_env(), check=True, timeout=120)
    reports = [json.loads(Path(f"{out}.{rank}").read_text()) for rank in (0, 1)]
    for report in reports:
        assert report["gathered"] == [
            {"rank": 0, "files": {"a.pt": [3, "ff"]}},
            {"rank": 1, "files": {"a.pt": [3, "ff"]}},
        ]
        assert report["broadcast"] == {"kind": "committed", "step": 4}
        assert "not JSON serializable" in report["refused"]
    assert reports[1]["hostile"] in ("UnicodeDecodeError", "JSONDecodeError")
    assert not marker.exists(), "a pickle from a peer was loaded: code ran"
