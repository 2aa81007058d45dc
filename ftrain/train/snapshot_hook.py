"""The hook that saves policy snapshots during training (the format: ``ftrain.policy.snapshots``)."""

from __future__ import annotations

import json

import torch

from ftrain.ckpt.format import CorruptCheckpoint, commit, encode, read_manifest, recorded_metrics, step_dir, write_file
from ftrain.ckpt.retention import delete_step
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import StorageError
from ftrain.config import SnapshotConfig
from ftrain.errors import UserError
from ftrain.heartbeat import Phase
from ftrain.policy import export
from ftrain.policy.load import Policy
from ftrain.policy.model import OBS_GROUP
from ftrain.policy.snapshots import ACTOR, FILE_NAMES, LINEAGE, PoliciesView, prune
from ftrain.train.hooks import Hook, TrainerView


def write_snapshot(
    storage: PoliciesView, policy: Policy, formats: list[str], observations: torch.Tensor, lineage: dict
) -> dict:
    """Write and commit snapshot ``policy.step`` into a fresh directory; its manifest."""
    step = policy.step
    contents = {FILE_NAMES[fmt]: export.encode(policy, fmt, observations) for fmt in formats}
    contents[ACTOR] = encode(policy.actor.state_dict())
    contents[LINEAGE] = (json.dumps(lineage, indent=2) + "\n").encode()
    files = {name: write_file(storage, step, name, data) for name, data in contents.items()}
    meta = {
        "kind": "policy_snapshot",
        "formats": {fmt: FILE_NAMES[fmt] for fmt in formats},
        "state_sha256": policy.digest,
        "config_hash": lineage["config_hash"],
        "config": policy.config.public_dict(),
        "robot": lineage["robot"],
    }
    return commit(storage, step, files, meta)


class PolicySnapshotHook(Hook):
    """Every ``snapshots.every`` iterations, on rank 0, a verified snapshot of the policy, then retention."""

    def __init__(self, config: SnapshotConfig) -> None:
        if "onnx" in config.formats:
            try:
                import onnxruntime  # noqa: F401 - every ONNX snapshot is run once to verify it
            except ImportError:
                raise UserError(
                    "snapshots.formats includes onnx, which needs onnxruntime: pip install 'ftrain[export]' "
                    "or set snapshots.formats=[torchscript]"
                ) from None
        self.config = config
        self.every = config.every
        self.storage: PoliciesView | None = None
        self.parent: dict | None = None

    def on_start(self, trainer: TrainerView) -> None:
        if not trainer.info.is_main:
            return
        self.storage = PoliciesView(trainer.checkpointer.storage)
        committed = trainer.checkpointer.committed_step
        if committed is not None:
            self._set_parent(trainer, committed, read_manifest(trainer.checkpointer.storage, committed))
        # snapshots past the step this run starts from belong to iterations it will redo (or to another history)
        for info in scan(self.storage):
            if info.step > trainer.iteration:
                trainer.log(f"deleting policy snapshot step {info.step} ({info.status}): newer than the start")
                delete_step(self.storage, info.step)

    def on_checkpoint(self, trainer: TrainerView, step: int, manifest: dict) -> None:
        if trainer.info.is_main:
            self._set_parent(trainer, step, manifest)

    def _set_parent(self, trainer: TrainerView, step: int, manifest: dict) -> None:
        """Remember the newest committed checkpoint: the lineage of the snapshots that follow."""
        where = trainer.checkpointer.storage.where(step_dir(step))
        self.parent = {"step": step, "url": where, "state_sha256": manifest["state_sha256"]}

    def after_iteration(self, trainer: TrainerView, metrics: dict[str, float]) -> None:
        if not trainer.info.is_main:
            return
        step = trainer.iteration
        config = trainer.config
        trainer.heartbeat.beat(Phase.SNAPSHOT, step)  # a phase of its own for the supervisor's timing: seconds
        policy = Policy(trainer.alg.get_policy(), config, self.storage.url, step, None, trainer.learned_digest())
        lineage = {
            "step": step,
            "state_sha256": policy.digest,
            "committed_checkpoint": self.parent,
            "config_hash": config.training_hash(trainer.env.robot),
            "env_id": config.env.id,
            "robot": trainer.env.robot,
            "metrics": recorded_metrics(metrics),
        }
        observations = trainer.env.get_observations()[OBS_GROUP]
        try:
            write_snapshot(self.storage, policy, self.config.formats, observations, lineage)
            prune(self.storage, self.config.keep_last)
        except (StorageError, OSError, CorruptCheckpoint) as exc:  # a lost snapshot does not stop training
            trainer.log(f"policy snapshot step {step} failed, training goes on: {exc}")
