"""``ftrain ckpt ls|verify|show|prune|unquarantine``: inspect and tidy the checkpoints of a run; each returns an
exit code.

A URL is a run's storage root (the directory holding ``checkpoints/``) or one step directory
(``<root>/checkpoints/step-000000120``). Bad input raises UserError.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Iterable

from ftrain.ckpt.format import (
    CHECKPOINTS,
    INCOMPLETE,
    QUARANTINE,
    VERIFIED,
    Verification,
    parse_checkpoint_url,
    step_dir,
    verify_step,
)
from ftrain.ckpt.retention import delete_step, retention_plan
from ftrain.ckpt.steps import ASIDE, scan, select_resume, set_aside_steps
from ftrain.ckpt.steps import unquarantine as unquarantine_step
from ftrain.ckpt.storage import Storage
from ftrain.errors import UserError

_UNITS = ("B", "KiB", "MiB", "GiB", "TiB")


def ls(url: str, options: dict | None = None) -> int:
    """One line per step: step, status, size, created, metrics (or, when not verified, the problems)."""
    storage, step = _open(url, options)
    infos = [info for info in scan(storage) if step is None or info.step == step]
    print(f"{'step':>10}  {'status':<11}  {'size':>9}  {'created':<20}  metrics / problems")
    for info in infos:
        fields = [" ".join(f"{k}={_number(v)}" for k, v in info.metrics.items()), *map(str, info.problems)]
        detail = "; ".join(field for field in fields if field)
        created = str((info.manifest or {}).get("created", "-"))
        print(f"{info.step:>10}  {info.status:<11}  {_size(info.size):>9}  {created:<20}  {detail}")
    if step is None:
        for directory, reason in set_aside_steps(storage):
            print(f"set aside: {storage.where(f'{ASIDE}/{directory}')} ({reason})")
    return 0


def verify(url: str, options: dict | None = None) -> int:
    """Verify every step (or the one step) with full digests: 0 if all verify, 1 otherwise, naming each failure."""
    storage, step = _open(url, options)
    steps = [step] if step is not None else [info.step for info in scan(storage)]
    failed = 0
    for each in steps:
        result = verify_step(storage, each, full=True)
        print(f"step {each}: {'ok' if result.ok else 'FAILED'}")
        for problem in result.problems:
            print(f"  {step_dir(each)}/{problem}")
        failed += not result.ok
    print(f"{len(steps) - failed} of {len(steps)} steps verified")
    return 1 if failed else 0


def show(url: str, options: dict | None = None, as_json: bool = False) -> int:
    """The manifest of one step, or of the newest verified step under a run's storage."""
    storage, step = _open(url, options)
    if step is None:
        selected = select_resume(storage, log=lambda line: print(line, file=sys.stderr), quarantine_bad=False)
        if selected is None:
            raise UserError(f"no verified checkpoint under {storage.url}: see ftrain ckpt ls {storage.url}")
        step, manifest = selected
        result = Verification(step, manifest=manifest)
    else:
        result = verify_step(storage, step, full=True)
        if result.manifest is None:
            problems = "; ".join(str(p) for p in result.problems)
            raise UserError(f"{storage.where(step_dir(step))} has no usable manifest ({problems})")
    if as_json:
        print(json.dumps(result.manifest, indent=2))
        return 0
    status = "verified" if result.ok else "NOT verified: " + "; ".join(str(p) for p in result.problems)
    print(f"checkpoint {storage.where(step_dir(step))} ({status})")
    for key, value in result.manifest.items():
        if key == "robot":
            _print_robot(value)
        elif key == "files":
            print("files:")
            for name, entry in value.items():
                print(f"  {name:<20} {_size(entry['size']):>9}  sha256 {entry['sha256']}")
        elif isinstance(value, dict):
            print(f"{key}:")
            for sub, item in value.items():
                print(f"  {sub}: {json.dumps(item)}")
        else:
            print(f"{key}: {value}")
    return 0


def _print_robot(robot: dict) -> None:
    """The identity of the robot a step was trained on: its env class, its model's files, its Python state."""
    origin = "gymnasium's own" if robot["builtin"] else "your own"
    print(f"robot: {robot['env_class']} ({origin}; identity {robot['digest']}; Python state {robot['python_state']})")
    for name, digest in robot["mjcf"].items():
        print(f"  {name:<30} sha256 {digest}")


def prune(
    url: str,
    keep_last: int,
    keep_best: int = 0,
    best_metric: str = "mean_return",
    keep_every: int = 0,
    pinned: Iterable[int] = (),
    dry_run: bool = False,
    options: dict | None = None,
    drop_bad: bool = False,
) -> int:
    """Apply the retention rules of ``checkpoint.retention_plan`` to a run's storage (``dry_run``: only print)."""
    for name, value in {"keep-last": keep_last, "keep-best": keep_best, "keep-every": keep_every}.items():
        if value < 0:
            raise UserError(f"--{name}={value} must be 0 or more")
    storage, step = _open(url, options)
    if step is not None:
        raise UserError(f"prune works on a run's storage, not one step: pass {storage.url}")
    infos = scan(storage, full=True)  # digests too: a bit-rotted step must not pass for the newest good one
    doomed = set(retention_plan(infos, keep_last, keep_best, best_metric, keep_every, pinned, drop_bad))
    for info in infos:
        if info.step in doomed:
            why = {VERIFIED: "verified, outside retention", INCOMPLETE: "abandoned, never committed"}.get(
                info.status, info.status
            )
            print(f"{'would delete' if dry_run else 'deleting'} step {info.step} ({why})")
            if not dry_run:
                delete_step(storage, info.step, info.files)
    if drop_bad:
        for directory, reason in set_aside_steps(storage):
            print(f"{'would delete' if dry_run else 'deleting'} {ASIDE}/{directory} (set aside: {reason})")
            if not dry_run:
                storage.delete_tree(f"{ASIDE}/{directory}")
    kept = [str(info.step) for info in infos if info.step not in doomed]
    print(f"{'would keep' if dry_run else 'kept'} {len(kept)} steps: {', '.join(kept) or '-'}")
    return 0


def unquarantine(url: str, options: dict | None = None) -> int:
    """Lift the quarantine of one step if all its files verify (full digests): 0 if lifted, 1 if it does not
    verify (the step stays quarantined)."""
    storage, step = _open(url, options)
    if step is None:
        raise UserError(
            f"unquarantine works on one step: pass {storage.url}/{CHECKPOINTS}/step-<N> (see ftrain ckpt ls)"
        )
    info = next(info for info in scan(storage) if info.step == step)
    if info.status != QUARANTINE:
        raise UserError(f"{storage.where(step_dir(step))} is {info.status}, not quarantined: nothing to lift")
    result = unquarantine_step(storage, step)
    if not result.ok:
        print(f"{storage.where(step_dir(step))} stays quarantined: it does not verify")
        for problem in result.problems:
            print(f"  {problem}")
        return 1
    print(f"{storage.where(step_dir(step))} verifies: quarantine lifted (was: {info.problems[0].reason})")
    return 0


def _open(url: str, options: dict | None) -> tuple[Storage, int | None]:
    """The storage and, for the URL of one step, the step; UserError if no checkpoint is there."""
    root, step = parse_checkpoint_url(url)
    storage = Storage.open(root, options)
    if step is None and not storage.list_dirs(CHECKPOINTS):
        raise UserError(
            f"no checkpoints under {storage.url}: pass a run's storage (the directory holding checkpoints/) "
            "or one step directory"
        )
    if step is not None and not storage.list_files(step_dir(step)):
        raise UserError(f"{storage.where(step_dir(step))} does not exist: see ftrain ckpt ls {storage.url}")
    return storage, step


def _size(n: int) -> str:
    value, unit = float(n), 0
    while value >= 1024 and unit < len(_UNITS) - 1:
        value, unit = value / 1024, unit + 1
    return f"{n} B" if unit == 0 else f"{value:.1f} {_UNITS[unit]}"


def _number(value: object) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)
