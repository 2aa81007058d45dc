"""Policy snapshots: deployable policies saved during training, by the same verify-before-trust rules as checkpoints.

Layout under a run's storage::

    policies/step-000000120/
      policy.pt       TorchScript   } self-contained, verified against the actor when written
      policy.onnx     ONNX          } (the formats are ``snapshots.formats``)
      actor.pt        the actor's state dict (weights_only), so ftrain loads the full policy (play, teacher)
      lineage.json    step, state digest, newest committed checkpoint, config hash, metrics
      MANIFEST.json   written last with exclusive create: size and SHA-256 of every file, config, state digest

A snapshot is trusted only if its manifest verifies. Writing, verifying, listing and pruning are checkpoint.py's own
functions, run on a view of the storage in which their ``checkpoints/`` directory stands for ``policies/``.
Snapshots have their own retention (``snapshots.keep_last``), independent of the checkpoints'.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

import torch

from ftrain import checkpoint
from ftrain.config import SnapshotConfig
from ftrain.envs import OBS_GROUP
from ftrain.errors import UserError
from ftrain.hooks import Hook
from ftrain.policy import Policy, encode
from ftrain.storage import Storage, StorageError

if TYPE_CHECKING:
    from ftrain.trainer import Trainer

POLICIES = "policies"
ACTOR = "actor.pt"
LINEAGE = "lineage.json"
FILE_NAMES = {"torchscript": "policy.pt", "onnx": "policy.onnx"}


class PoliciesView:
    """``storage`` as checkpoint.py's functions see it: their ``checkpoints/`` directory is ``policies/``."""

    def __init__(self, storage: Storage) -> None:
        self.storage = storage
        self.url = storage.url

    def read(self, rel: str) -> bytes:
        return self.storage.read(_policies(rel))

    def write_exclusive(self, rel: str, data: bytes) -> None:
        self.storage.write_exclusive(_policies(rel), data)

    def list_files(self, rel: str) -> dict[str, int]:
        return self.storage.list_files(_policies(rel))

    def list_dirs(self, rel: str) -> list[str]:
        return self.storage.list_dirs(_policies(rel))

    def delete(self, rel: str) -> None:
        self.storage.delete(_policies(rel))

    def delete_tree(self, rel: str) -> None:
        self.storage.delete_tree(_policies(rel))

    def where(self, rel: str = "") -> str:
        return self.storage.where(_policies(rel))


def _policies(rel: str) -> str:
    head, sep, rest = rel.partition("/")
    return POLICIES + sep + rest if head == checkpoint.CHECKPOINTS else rel


def parse_snapshot_url(url: str) -> tuple[str, int] | None:
    """Root and step of a snapshot URL ``<root>/policies/step-000000120``; None for any other URL."""
    head, _, last = url.rstrip("/").rpartition("/")
    if head.rpartition("/")[2] != POLICIES:
        return None
    root, step = checkpoint.parse_checkpoint_url(f"{head[: -len(POLICIES)]}{checkpoint.CHECKPOINTS}/{last}")
    return None if step is None else (root, step)


def open_snapshot(url: str, options: dict | None = None) -> tuple[PoliciesView, int, dict]:
    """The storage view, step and verified manifest of the snapshot at ``url``; UserError if it does not verify."""
    root, step = parse_snapshot_url(url)
    storage = PoliciesView(Storage.open(root, options))
    result = checkpoint.verify(storage, step)
    if not result.ok:
        problems = "; ".join(str(p) for p in result.problems)
        raise UserError(
            f"policy snapshot {storage.where(checkpoint.step_dir(step))} does not verify ({problems}): "
            "pick another step"
        )
    return storage, step, result.manifest


def write_snapshot(
    storage: PoliciesView, policy: Policy, formats: list[str], observations: torch.Tensor, lineage: dict
) -> dict:
    """Write and commit snapshot ``policy.step`` into a fresh directory; its manifest."""
    step = policy.step
    contents = {FILE_NAMES[fmt]: encode(policy, fmt, observations) for fmt in formats}
    contents[ACTOR] = checkpoint.encode(policy.actor.state_dict())
    contents[LINEAGE] = (json.dumps(lineage, indent=2) + "\n").encode()
    files = {name: checkpoint.write_file(storage, step, name, data) for name, data in contents.items()}
    meta = {
        "kind": "policy_snapshot",
        "formats": {fmt: FILE_NAMES[fmt] for fmt in formats},
        "state_sha256": policy.digest,
        "config_hash": policy.config.training_hash(),
        "config": policy.config.public_dict(),
    }
    return checkpoint.commit(storage, step, files, meta)


def prune(storage: PoliciesView, keep_last: int) -> None:
    """Delete all but the last ``keep_last`` verified snapshots (and abandoned ones older than the newest)."""
    for step in checkpoint.retention_plan(checkpoint.scan(storage), keep_last):
        checkpoint.delete_step(storage, step)


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

    def on_start(self, trainer: Trainer) -> None:
        if not trainer.info.is_main:
            return
        self.storage = PoliciesView(trainer.checkpointer.storage)
        committed = trainer.checkpointer.committed_step
        if committed is not None:
            self._set_parent(trainer, committed, checkpoint.read_manifest(trainer.checkpointer.storage, committed))
        # snapshots past the step this run starts from belong to iterations it will redo (or to another history)
        for info in checkpoint.scan(self.storage):
            if info.step > trainer.iteration:
                trainer.log(f"deleting policy snapshot step {info.step} ({info.status}): newer than the start")
                checkpoint.delete_step(self.storage, info.step)

    def on_checkpoint(self, trainer: Trainer, step: int, manifest: dict) -> None:
        if trainer.info.is_main:
            self._set_parent(trainer, step, manifest)

    def _set_parent(self, trainer: Trainer, step: int, manifest: dict) -> None:
        """Remember the newest committed checkpoint: the lineage of the snapshots that follow."""
        where = trainer.checkpointer.storage.where(checkpoint.step_dir(step))
        self.parent = {"step": step, "url": where, "state_sha256": manifest["state_sha256"]}

    def after_iteration(self, trainer: Trainer, metrics: dict[str, float]) -> None:
        if not trainer.info.is_main:
            return
        step = trainer.iteration
        config = trainer.config
        policy = Policy(trainer.alg.get_policy(), config, self.storage.url, step, None, trainer.learned_digest())
        lineage = {
            "step": step,
            "state_sha256": policy.digest,
            "committed_checkpoint": self.parent,
            "config_hash": config.training_hash(),
            "env_id": config.env.id,
            "metrics": {key: value for key, value in metrics.items() if not key.endswith("_time")},
        }
        observations = trainer.env.get_observations()[OBS_GROUP]
        try:
            write_snapshot(self.storage, policy, self.config.formats, observations, lineage)
            prune(self.storage, self.config.keep_last)
        except (StorageError, OSError, checkpoint.CorruptCheckpoint) as exc:  # a lost snapshot does not stop training
            trainer.log(f"policy snapshot step {step} failed, training goes on: {exc}")
