"""The supervisor's decisions as numbers a tracker can chart: restarts, resizes, iterations lost and downtime so far,
from ``<log_dir>/events.jsonl`` (``ftrain.supervise.events``), re-read only when it has grown."""

from __future__ import annotations

import json
from pathlib import Path

from ftrain.values import is_number


class SupervisorTotals:
    def __init__(self, log_dir: str) -> None:
        self.path = Path(log_dir) / "events.jsonl"
        self._size = -1
        self._totals: dict[str, float] = {}

    def __call__(self) -> dict[str, float]:
        """Empty for a run that is not supervised."""
        try:
            size = self.path.stat().st_size
        except OSError:
            return {}
        if size != self._size:
            self._size = size
            self._totals = totals(self.path.read_text().splitlines())
        return self._totals


def totals(lines: list[str]) -> dict[str, float]:
    """Counted as the supervisor's summary counts them while workers run: iterations lost and downtime of recoveries
    (a failure never recovered from is counted by the summary as the run ends, when no worker charts)."""
    events = [event for event in map(_parse, lines) if event]
    recovered = [event for event in events if event.get("event") == "recovered"]
    return {
        "supervisor/restarts": sum(event.get("event") == "restart" for event in events),
        "supervisor/resizes": sum(event.get("event") == "resize" for event in events),
        "supervisor/iterations_lost": sum(_counted(event.get("lost")) for event in recovered),
        "supervisor/downtime": sum(_counted(event.get("downtime")) for event in recovered),
    }


def _counted(value: object) -> float:
    """What the supervisor wrote (iterations, seconds), or 0 for a value damaged since: a tracker must not fail."""
    return value if is_number(value) else 0


def _parse(line: str) -> dict:
    """A line being written may be incomplete: it counts once it is whole."""
    try:
        event = json.loads(line)
    except (ValueError, RecursionError):  # RecursionError: arrays nested thousands deep, no line the supervisor wrote
        return {}
    return event if isinstance(event, dict) else {}
