"""``<log_dir>/tracking.json``: the tracker run a training run logs to, for a restart before the first checkpoint
(which carries the id from then on)."""

from __future__ import annotations

import json
from pathlib import Path

from ftrain.files import replace_text


def recorded_run(log_dir: str, storage: str) -> str:
    """The run id recorded for ``storage`` in ``log_dir`` ("" when there is none)."""
    try:
        data = json.loads((Path(log_dir) / "tracking.json").read_text())
    except (OSError, ValueError):
        return ""
    return data.get("run_id", "") if isinstance(data, dict) and data.get("storage") == storage else ""


def record_run(log_dir: str, run_id: str, storage: str) -> None:
    path = Path(log_dir) / "tracking.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_text(path, json.dumps({"run_id": run_id, "storage": storage}))
