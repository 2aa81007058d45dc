"""MLflow: the run tagged with ftrain's run id (``ftrain.run_id``) in the experiment, created on the first start and
continued by every later one; the last step it holds comes from its own metric history. Imported lazily: MLflow is
an optional extra."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

from ftrain.config import MlflowConfig
from ftrain.values import dotted

if TYPE_CHECKING:
    from ftrain.track.sender import RunInfo

RUN_TAG = "ftrain.run_id"
STEP_METRIC = "env_steps"
"""A metric of every iteration: its history says which steps the run holds."""
PARAMS_PER_BATCH = 100
"""MLflow's limit of params in one ``log_batch``."""


class MlflowRun:
    name = "mlflow"

    def __init__(self, config: MlflowConfig, run: RunInfo) -> None:
        self.config = config
        self.info = run
        self.client = None
        self.run_id = ""

    def open(self) -> int:
        from mlflow.entities import Param
        from mlflow.tracking import MlflowClient

        self.client = client = MlflowClient(self.config.tracking_uri.reveal() or None)
        name = self.config.experiment or self.info.name
        experiment = client.get_experiment_by_name(name)
        experiment_id = experiment.experiment_id if experiment else client.create_experiment(name)
        found = client.search_runs([experiment_id], f"tags.`{RUN_TAG}` = '{self.info.run_id}'", max_results=1)
        logged: dict[str, str] = {}
        if found:
            self.run_id, logged = found[0].info.run_id, found[0].data.params
            client.update_run(self.run_id, status="RUNNING")
            last = max((metric.step for metric in client.get_metric_history(self.run_id, STEP_METRIC)), default=-1)
        else:
            tags = {RUN_TAG: self.info.run_id}
            self.run_id = client.create_run(experiment_id, tags=tags, run_name=self.info.name).info.run_id
            last = -1
        # params are fixed once logged: the config as it was at the start (config.json follows changes); those a start
        # killed between making the run and logging them did not log are logged by the next
        params = [Param(key, str(value)) for key, value in dotted(self.info.config).items() if key not in logged]
        for start in range(0, len(params), PARAMS_PER_BATCH):
            client.log_batch(self.run_id, params=params[start : start + PARAMS_PER_BATCH])
        for key, value in self.info.identity.items():
            client.set_tag(self.run_id, f"ftrain.{key}", value)
        client.log_dict(self.run_id, self.info.config, "ftrain/config.json")
        return last

    def log(self, step: int, values: dict[str, float]) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        self.client.log_batch(self.run_id, metrics=[Metric(key, value, now, step) for key, value in values.items()])

    def close(self, finished: bool) -> None:
        self.client.set_terminated(self.run_id, "FINISHED" if finished else "KILLED")
