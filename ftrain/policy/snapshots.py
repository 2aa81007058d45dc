"""Policy snapshots: deployable policies saved during training, by the same verify-before-trust rules as checkpoints.

Layout under a run's storage::

    policies/step-000000120/
      policy.pt       TorchScript   } self-contained, verified against the actor when written
      policy.onnx     ONNX          } (the formats are ``snapshots.formats``)
      actor.pt        the actor's state dict (weights_only), so ftrain loads the full policy (play, teacher)
      lineage.json    step, state digest, newest committed checkpoint, config hash, metrics
      MANIFEST.json   written last with exclusive create: size and SHA-256 of every file, config, state digest

A snapshot is trusted only if its manifest verifies. Writing, verifying, listing and pruning are ftrain.ckpt's own
functions, run on a view of the storage in which their ``checkpoints/`` directory stands for ``policies/``.
Snapshots have their own retention (``snapshots.keep_last``), independent of the checkpoints'.
"""

from __future__ import annotations

from ftrain.ckpt.commands import verify_each
from ftrain.ckpt.format import CHECKPOINTS, INCOMPLETE, POLICIES, parse_checkpoint_url, step_dir, verify_step
from ftrain.ckpt.retention import delete_step, retention_plan
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError, counted

ACTOR = "actor.pt"
LINEAGE = "lineage.json"
FILE_NAMES = {"torchscript": "policy.pt", "onnx": "policy.onnx"}


class PoliciesView:
    """``storage`` as ftrain.ckpt's functions see it: their ``checkpoints/`` directory is ``policies/``."""

    def __init__(self, storage: Storage) -> None:
        self.storage = storage
        self.url = storage.url

    def read(self, rel: str) -> bytes:
        return self.storage.read(_policies(rel))

    def write_exclusive(self, rel: str, data: bytes, commit: bool = False) -> None:
        self.storage.write_exclusive(_policies(rel), data, commit)

    def list_files(self, rel: str) -> dict[str, int]:
        return self.storage.list_files(_policies(rel))

    def list_dirs(self, rel: str) -> list[str]:
        return self.storage.list_dirs(_policies(rel))

    def delete(self, rel: str) -> None:
        self.storage.delete(_policies(rel))

    def delete_tree(self, rel: str) -> None:
        self.storage.delete_tree(_policies(rel))

    def modified(self, rel: str) -> float | None:
        return self.storage.modified(_policies(rel))

    def where(self, rel: str = "") -> str:
        return self.storage.where(_policies(rel))


def _policies(rel: str) -> str:
    head, sep, rest = rel.partition("/")
    return POLICIES + sep + rest if head == CHECKPOINTS else rel


def parse_snapshot_url(url: str) -> tuple[str, int] | None:
    """Root and step of a snapshot URL ``<root>/policies/step-000000120`` (or ``step-000000120`` in ``policies/``, as
    a checkpoint's); None for any other URL."""
    root, step = parse_checkpoint_url(url, POLICIES)
    return None if step is None else (root, step)


def open_snapshot(url: str, options: dict | None = None) -> tuple[PoliciesView, int, dict]:
    """The storage view, step and verified manifest of the snapshot at ``url``; UserError if it does not verify."""
    root, step = parse_snapshot_url(url)
    storage = PoliciesView(Storage.open(root, options))
    result = verify_step(storage, step)
    if not result.ok:
        problems = "; ".join(str(p) for p in result.problems)
        raise UserError(
            f"policy snapshot {storage.where(step_dir(step))} does not verify ({problems}): pick another step"
        )
    return storage, step, result.manifest


def verify(url: str, options: dict | None = None) -> int:
    """``ftrain ckpt verify`` of a snapshot (its URL), or of every snapshot of a run's storage: each file's size and
    SHA-256 against the manifest, a line per snapshot; 1 if one fails. A storage without snapshots prints nothing."""
    root, only = parse_snapshot_url(url) or (parse_checkpoint_url(url)[0], None)
    storage = PoliciesView(Storage.open(root, options))
    infos = [info for info in scan(storage) if only is None or info.step == only]
    if only is not None and not infos:
        raise UserError(f"policy snapshot {storage.where(step_dir(only))} does not exist: see {storage.where()}")
    failed, deleted = verify_each(storage, infos, "policy snapshot", POLICIES)
    if committed := sum(info.status != INCOMPLETE for info in infos) - deleted:
        print(f"{committed - failed} of {counted(committed, 'committed policy snapshot')} verified")
    return 1 if failed else 0


def prune(storage: PoliciesView, keep_last: int) -> None:
    """Delete all but the last ``keep_last`` verified snapshots (and abandoned ones older than the newest)."""
    for step in retention_plan(scan(storage), keep_last):
        delete_step(storage, step)
