"""Retention: which steps to delete after a commit, and deleting one step manifest first."""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable

from ftrain.ckpt.format import CORRUPT, INCOMPLETE, MANIFEST, QUARANTINE, VERIFIED, StepInfo, step_dir
from ftrain.ckpt.storage import Storage


def retention_plan(
    steps: Iterable[StepInfo],
    keep_last: int,
    keep_best: int = 0,
    best_metric: str = "mean_return",
    keep_every: int = 0,
    pinned: Iterable[int] = (),
    drop_bad: bool = False,
) -> list[int]:
    """Steps to delete, newest first.

    Kept: the last ``keep_last`` verified steps, the ``keep_best`` verified ones with the highest
    ``metrics[best_metric]``, multiples of ``keep_every``, ``pinned`` ones, and always the newest verified one.
    Deleted: other verified steps and incomplete (never committed) ones older than the newest verified step;
    an incomplete step newer than that may be a save in flight and is left alone. Corrupt and quarantined
    steps are kept for a human to look at, unless ``drop_bad``.
    """
    steps = sorted(steps, key=lambda info: info.step, reverse=True)
    verified = [info for info in steps if info.status == VERIFIED]
    if not verified:
        return [info.step for info in steps if drop_bad and info.status in (CORRUPT, QUARANTINE)]
    keep = {*pinned, *kept(verified, keep_last, keep_best, best_metric, keep_every, pinned)}
    newest = verified[0].step
    deletable = {VERIFIED, INCOMPLETE} | ({CORRUPT, QUARANTINE} if drop_bad else set())
    return [
        info.step
        for info in steps
        if info.status in deletable and info.step not in keep and not (info.status == INCOMPLETE and info.step > newest)
    ]


class Kept(enum.Enum):
    """Why retention keeps a verified step."""

    NEWEST = "newest"
    LAST = "last"
    BEST = "best"
    PINNED = "pinned"
    MILESTONE = "milestone"


def kept(
    verified: list[StepInfo],
    keep_last: int,
    keep_best: int = 0,
    best_metric: str = "mean_return",
    keep_every: int = 0,
    pinned: Iterable[int] = (),
) -> dict[int, list[Kept]]:
    """The steps of ``verified`` (newest first) that retention keeps, each with why (see ``retention_plan``)."""
    pinned = set(pinned)
    measured = [info for info in verified if _metric(info, best_metric) is not None]
    best = {info.step for info in sorted(measured, key=lambda info: -_metric(info, best_metric))[:keep_best]}
    reasons = {}
    for index, info in enumerate(verified):
        why = [
            reason
            for reason, holds in (
                (Kept.NEWEST, index == 0),
                (Kept.LAST, index < keep_last),
                (Kept.BEST, info.step in best),
                (Kept.PINNED, info.step in pinned),
                (Kept.MILESTONE, is_milestone(info.step, keep_every)),
            )
            if holds
        ]
        if why:
            reasons[info.step] = why
    return reasons


def is_milestone(step: int, keep_every: int) -> bool:
    """Whether ``checkpoint.keep_every`` makes ``step`` a milestone (0: none is)."""
    return keep_every > 0 and step % keep_every == 0


def promised(step: int, keep_every: int, pinned: Iterable[int]) -> bool:
    """Whether retention keeps ``step`` once it exists (pinned, a milestone): the schedule saves it, whatever the
    interval (``ftrain.ckpt.schedule``)."""
    return step in pinned or is_milestone(step, keep_every)


def delete_step(storage: Storage, step: int, files: Iterable[str] = ()) -> None:
    """Delete the manifest first (the step stops being committed), then the rest: given the names of its other
    ``files`` (its manifest's list), those without a listing (a request less on S3), else the directory's tree."""
    storage.delete(f"{step_dir(step)}/{MANIFEST}")
    files = list(files)
    if not files or not storage.delete_files(step_dir(step), files):
        storage.delete_tree(step_dir(step))


def _metric(info: StepInfo, name: str) -> float | None:
    value = info.metrics.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        return None
    return float(value)
