"""What a tracker is told about a training run, as plain data (no trainer), and the trackers a config turns on."""

from __future__ import annotations

from dataclasses import dataclass

from ftrain.config import Config
from ftrain.track.mlflow_run import MlflowRun
from ftrain.track.sender import Tracker
from ftrain.track.wandb_run import WandbRun


@dataclass(frozen=True)
class RunInfo:
    run_id: str
    """ftrain's id of the tracker run: W&B's run id, an MLflow tag (MLflow makes its own ids)."""
    name: str
    config: dict
    """The resolved config, credentials redacted (``Config.public_dict``)."""
    identity: dict[str, str | int]
    """Config hash, storage URL (redacted), world size of this start."""
    log_dir: str


def trackers(config: Config, run: RunInfo) -> list[Tracker]:
    """The trackers ``config.log`` turns on (their libraries are imported only when they open)."""
    found: list[Tracker] = []
    if config.log.wandb.enabled:
        found.append(WandbRun(config.log.wandb, run))
    if config.log.mlflow.enabled:
        found.append(MlflowRun(config.log.mlflow, run))
    return found
