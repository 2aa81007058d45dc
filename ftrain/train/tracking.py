"""The hook that feeds W&B and MLflow (``log.wandb``, ``log.mlflow``) from rank 0: one tracker run per training
run, across every restart and resize.

The tracker run's id is this hook's state, so it travels in every checkpoint and a resumed run continues the same
tracker run; before the first checkpoint a restart finds it in the local record (``ftrain.track.record``). A run
that starts afresh (``resume=never``, a new storage) gets a new id. Rows a tracker lost up to the step resumed from
(a killed process had not sent them) are sent again from ``metrics.csv`` (``log.csv``). Nothing here draws from a
random stream the training uses (``uuid4`` reads the OS's entropy) or decides anything by the clock.
"""

from __future__ import annotations

import uuid

from ftrain.config import Config, storage_identity
from ftrain.track.record import record_run, recorded_run
from ftrain.track.run import trackers
from ftrain.track.sender import RunInfo, Sender
from ftrain.track.supervisor_totals import SupervisorTotals
from ftrain.train.hooks import Hook, TrainerView, read_metrics


class TrackingHook(Hook):
    def __init__(self, config: Config) -> None:
        self.config = config
        self.storage = storage_identity(config.storage.url)
        self.run_id = ""
        self.senders: list[Sender] = []

    def state_dict(self) -> dict:
        return {"run_id": self.run_id, "storage": self.storage}

    def load_state_dict(self, state: dict) -> None:
        """A checkpoint of another storage (``resume=`` a step of another run) starts a training run of its own."""
        self.run_id = state["run_id"] if state.get("storage") == self.storage else ""

    def on_start(self, trainer: TrainerView) -> None:
        if not trainer.info.is_main:
            return
        config, storage = self.config, self.storage
        continued = config.resume == "auto" and recorded_run(config.log_dir, storage)
        self.run_id = self.run_id or continued or uuid.uuid4().hex[:16]
        record_run(config.log_dir, self.run_id, storage)
        run = RunInfo(
            run_id=self.run_id,
            name=config.name,
            config=config.public_dict(),
            identity={
                "config_hash": config.training_hash(trainer.env.robot),
                "storage": storage,
                "world_size": trainer.info.world_size,
            },
            log_dir=config.log_dir,
        )
        resumed = trainer.iteration
        earlier = lambda last: read_metrics(config.log_dir, last, resumed)  # noqa: E731 - what the CSV hook kept
        self.senders = [
            Sender(tracker, earlier, SupervisorTotals(config.log_dir), trainer.log) for tracker in trackers(config, run)
        ]

    def after_iteration(self, trainer: TrainerView, metrics: dict[str, float]) -> None:
        for sender in self.senders:  # empty but on rank 0
            sender.send(trainer.iteration, metrics)

    def on_end(self, trainer: TrainerView) -> None:
        for sender in self.senders:
            sender.close(finished=trainer.iteration >= self.config.iterations)
