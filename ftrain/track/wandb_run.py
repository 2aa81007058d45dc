"""Weights & Biases: the run's id is ftrain's, so every start of a training run continues one W&B run
(``resume="allow"``); offline, each start writes its own directory under ``<log_dir>/wandb`` (``$WANDB_DIR/wandb``
where the user set that, as W&B itself does) and ``wandb sync`` joins them. Imported lazily: W&B is an optional
extra."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from ftrain.config import WandbConfig
from ftrain.track.wandb_log import last_offline_step

if TYPE_CHECKING:
    from ftrain.track.sender import RunInfo


class WandbRun:
    name = "wandb"

    def __init__(self, config: WandbConfig, run: RunInfo) -> None:
        self.config = config
        self.info = run
        self.run = None

    def open(self) -> int:
        import wandb

        config = self.config
        self.run = wandb.init(
            project=config.project or self.info.name,
            entity=config.entity or None,
            group=config.group or None,
            tags=config.tags or None,
            mode=config.mode or None,
            id=self.info.run_id,
            resume="allow",
            name=self.info.name,
            dir=os.environ.get("WANDB_DIR") or self.info.log_dir,
            config={**self.info.config, "ftrain": self.info.identity},
            allow_val_change=True,  # a resize changes the world size; allow_config_change the config
            settings=wandb.Settings(console="off", silent=True),
            reinit="create_new",
        )
        if self.run.offline:  # each start has a directory of its own; what the earlier ones wrote is on disk
            return last_offline_step(Path(self.run.dir).parents[1], self.info.run_id)
        return self.run.starting_step - 1  # a resumed online run starts past the last step the server holds

    def log(self, step: int, values: dict[str, float]) -> None:
        self.run.log(values, step=step)

    def close(self, finished: bool) -> None:
        self.run.finish(exit_code=0 if finished else 1)
