"""The trackers a config turns on (what each is told and what each implements: ``sender.py``)."""

from __future__ import annotations

from ftrain.config import Config
from ftrain.track.mlflow_run import MlflowRun
from ftrain.track.sender import RunInfo, Tracker
from ftrain.track.wandb_run import WandbRun


def trackers(config: Config, run: RunInfo) -> list[Tracker]:
    """The trackers ``config.log`` turns on (their libraries are imported only when they open)."""
    found: list[Tracker] = []
    if config.log.wandb.enabled:
        found.append(WandbRun(config.log.wandb, run))
    if config.log.mlflow.enabled:
        found.append(MlflowRun(config.log.mlflow, run))
    return found
