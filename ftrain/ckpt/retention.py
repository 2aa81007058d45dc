"""Retention: which steps to delete after a commit, and deleting one step manifest first."""

from __future__ import annotations

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
    keep = {verified[0].step, *pinned}
    keep |= {info.step for info in verified[:keep_last]} | set(best_steps(verified, keep_best, best_metric))
    if keep_every > 0:
        keep |= {info.step for info in verified if info.step % keep_every == 0}
    newest = verified[0].step
    deletable = {VERIFIED, INCOMPLETE} | ({CORRUPT, QUARANTINE} if drop_bad else set())
    return [
        info.step
        for info in steps
        if info.status in deletable and info.step not in keep and not (info.status == INCOMPLETE and info.step > newest)
    ]


def best_steps(steps: Iterable[StepInfo], count: int, metric: str) -> list[int]:
    """The ``count`` verified steps with the highest ``metrics[metric]`` (steps without it do not count), best
    first."""
    ranked = sorted(
        (info for info in steps if info.status == VERIFIED and _metric(info, metric) is not None),
        key=lambda info: -_metric(info, metric),
    )
    return [info.step for info in ranked[:count]]


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
