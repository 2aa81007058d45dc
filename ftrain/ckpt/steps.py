"""What is in a storage: the state of every step, resume selection, quarantine, and clearing for a new save.

Rules (see ``format.py`` for what "verified" means): a corrupt committed step is quarantined, never loaded and
never deleted except by an explicit prune; an incomplete one (no manifest) was abandoned and may be deleted.
"""

from __future__ import annotations

import json
from collections.abc import Callable

from ftrain.ckpt.format import (
    CHECKPOINTS,
    CORRUPT,
    INCOMPLETE,
    MANIFEST,
    QUARANTINE,
    QUARANTINED,
    STEP_DIR,
    VERIFIED,
    CorruptCheckpoint,
    Problem,
    StepInfo,
    now,
    parse_checkpoint_url,
    read_manifest,
    step_dir,
    verify_listed,
    verify_step,
)
from ftrain.ckpt.retention import delete_step
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError


def scan(storage: Storage, full: bool = False) -> list[StepInfo]:
    """Every step directory, newest first. ``full`` checks digests too (reads every file); else sizes only."""
    infos = []
    for name in storage.list_dirs(CHECKPOINTS):
        match = STEP_DIR.match(name)
        if match is None:
            continue
        step = int(match[1])
        present = storage.list_files(step_dir(step))
        size = sum(present.values())
        if QUARANTINED in present:
            reason = _quarantine_reason(storage, step)
            infos.append(
                StepInfo(step, QUARANTINE, size, _manifest_or_none(storage, step), [Problem(QUARANTINED, reason)])
            )
            continue
        result = verify_listed(storage, step, present, full)
        status = VERIFIED if result.ok else INCOMPLETE if MANIFEST not in present else CORRUPT
        strays = bool(result.manifest) and bool(present.keys() - result.manifest["files"].keys() - {MANIFEST})
        infos.append(StepInfo(step, status, size, result.manifest, result.problems, strays))
    return sorted(infos, key=lambda info: info.step, reverse=True)


def quarantine(storage: Storage, step: int, reason: str) -> None:
    """Mark ``step`` as never to be loaded again; its data stays for a human to inspect."""
    marker = {"step": step, "reason": reason, "time": now()}
    storage.write_replace(f"{step_dir(step)}/{QUARANTINED}", (json.dumps(marker, indent=2) + "\n").encode())


def select_resume(
    storage: Storage, log: Callable[[str], None] = print, quarantine_bad: bool = True
) -> tuple[int, dict] | None:
    """The newest step that fully verifies, with its manifest; None if there is none.

    Each newer step that is skipped is reported through ``log`` with the reason; a committed step that fails
    verification is quarantined (unless ``quarantine_bad`` is False, e.g. for someone else's read-only run).
    """
    for info in scan(storage):
        status, problems = info.status, info.problems
        if status == VERIFIED:
            result = verify_step(storage, info.step, full=True)
            if result.ok:
                return info.step, result.manifest
            status, problems = CORRUPT, result.problems
        reasons = "; ".join(str(p) for p in problems)
        if status == CORRUPT and quarantine_bad:
            quarantine(storage, info.step, reasons)
            log(f"skipping checkpoint step {info.step}: corrupt, quarantined ({reasons})")
        else:
            log(f"skipping checkpoint step {info.step}: {status} ({reasons})")
    return None


def clear_newer(storage: Storage, step: int, log: Callable[[str], None] = print) -> list[int]:
    """Prepare a run starting from ``step`` (0 for a fresh start) to save the following steps again.

    Every save needs a fresh directory. Incomplete steps newer than ``step`` were abandoned by the run that died
    (never committed): they are deleted. Corrupt and quarantined ones are kept for a human to inspect and
    returned: the run replaces each only when it saves that very step again (:func:`replace_bad`). A verified newer
    step means the storage holds another history: UserError, nothing deleted. Call it on rank 0 before the first
    save, when no other process writes to this storage.
    """
    newer = [info for info in scan(storage) if info.step > step]
    verified = [info.step for info in newer if info.status == VERIFIED]
    if verified:
        raise UserError(
            f"{storage.url} already holds verified checkpoint step {verified[0]}, newer than step {step} this run "
            "starts from: resume from the newest step or use another storage"
        )
    for info in newer:
        if info.status == INCOMPLETE:
            log(f"deleting checkpoint step {info.step} (incomplete): newer than step {step} this run starts from")
            delete_step(storage, info.step)
    return [info.step for info in newer if info.status != INCOMPLETE]


def replace_bad(storage: Storage, step: int, log: Callable[[str], None] = print) -> None:
    """Delete corrupt or quarantined ``step`` so that a run that reached it again can save it afresh."""
    info = next((info for info in scan(storage) if info.step == step), None)
    if info is None:
        return
    if info.status == VERIFIED:
        raise UserError(f"{storage.where(step_dir(step))} is verified: refusing to replace it")
    reasons = "; ".join(str(problem) for problem in info.problems)
    log(f"replacing checkpoint step {step} ({info.status}: {reasons}) with a new save")
    delete_step(storage, step)


def resolve_checkpoint_url(
    url: str, options: dict | None = None, log: Callable[[str], None] = print
) -> tuple[Storage, int, dict]:
    """Storage, step and manifest of a checkpoint URL: one step directory, or a run's storage (its newest
    verified step). UserError if nothing verified is there. Never writes (nothing is quarantined)."""
    root, step = parse_checkpoint_url(url)
    storage = Storage.open(root, options)
    if step is None:
        selected = select_resume(storage, log, quarantine_bad=False)
        if selected is None:
            raise UserError(f"no verified checkpoint under {storage.url}: pass a run's storage or a step directory")
        return storage, *selected
    result = verify_step(storage, step)
    if not result.ok:
        problems = "; ".join(str(p) for p in result.problems)
        raise UserError(f"checkpoint {storage.where(step_dir(step))} does not verify ({problems}): pick another step")
    return storage, step, result.manifest


def _quarantine_reason(storage: Storage, step: int) -> str:
    try:
        return str(json.loads(storage.read(f"{step_dir(step)}/{QUARANTINED}"))["reason"])
    except (FileNotFoundError, ValueError, TypeError, KeyError):
        return "quarantined (marker unreadable)"


def _manifest_or_none(storage: Storage, step: int) -> dict | None:
    try:
        return read_manifest(storage, step)
    except (FileNotFoundError, CorruptCheckpoint):
        return None
