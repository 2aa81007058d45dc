"""``ftrain ckpt ls|verify|show|prune|unquarantine``: inspect and tidy the checkpoints of a run; each returns an
exit code.

A URL is a run's storage root (the directory holding ``checkpoints/``) or one step directory
(``<root>/checkpoints/step-000000120``; for ``unquarantine`` also one set aside, ``<root>/quarantine/step-...``).
Bad input raises UserError. The commands that write (``prune``, ``unquarantine``) hold the storage's lease while
they do (``as_lease_holder``): refused while a run holds it.
"""

from __future__ import annotations

import json
import secrets
import sys
import time
from collections.abc import Callable, Iterable

from ftrain.ckpt.fence import guarded
from ftrain.ckpt.format import (
    CHECKPOINTS,
    CORRUPT,
    INCOMPLETE,
    MANIFEST,
    QUARANTINE,
    VERIFIED,
    StepInfo,
    Verification,
    human_size,
    parse_checkpoint_url,
    shown,
    step_dir,
    verify_step,
)
from ftrain.ckpt.lease import LEASE, Lease, LeaseHeld, saving_now
from ftrain.ckpt.lineage import generation, history, listed_steps
from ftrain.ckpt.retention import Kept, delete_step, kept, retention_plan
from ftrain.ckpt.steps import (
    ASIDE,
    abandoned,
    aside_step,
    check_exists,
    part_of_a_storage,
    quarantine,
    reinstate,
    scan,
    select_resume,
    set_aside,
    set_aside_location,
    set_aside_steps,
    step_files,
    superseded_reason,
)
from ftrain.ckpt.steps import unquarantine as unquarantine_step
from ftrain.ckpt.storage import Storage
from ftrain.config import CheckpointConfig
from ftrain.errors import EXIT_STORAGE_HELD, StorageError, UserError, command, counted, did_you_mean
from ftrain.progress import Progress
from ftrain.values import is_number

WIDTH = 100
"""Columns of ``ls``'s table: it fits a terminal."""
METRICS = ("mean_return", "eval_return")
"""The metrics ``ls`` shows (a dash where a step has none)."""


def ls(url: str, options: dict | None = None) -> int:
    """A table of the steps, newest first: step, status, size, when created (UTC), the returns, and which steps
    retention keeps as the newest, the best, pinned or milestones (not those it keeps only as among the last few);
    under a step that is not committed whole, its problems. Manifests and file sizes only: ``verify`` reads every
    byte."""
    storage, step = _open(url, options)
    progress = Progress()
    progress.show("ckpt ls: reading the steps' manifests...")
    every = scan(storage)
    progress.clear()
    marks = _marks(every)
    row = "{:>9}  {:<11}  {:>9}  {:<16}  {:>11}  {:>11}  {}"
    print(row.format("step", "status", "size", "created (UTC)", *METRICS, "kept as"))
    for info in (info for info in every if step is None or info.step == step):
        created = str((info.manifest or {}).get("created") or "-").replace("T", " ")[:16]
        returns = [_number(info.metrics.get(name)) for name in METRICS]
        why = ", ".join(reason.value for reason in marks.get(info.step, []) if reason is not Kept.LAST)
        print(row.format(info.step, shown(info.status), human_size(info.size), created, *returns, why).rstrip())
        for problem in info.problems:
            print(_fit(f"{'':>11}{problem}"))
    if step is None:
        for directory, reason in set_aside_steps(storage):
            print(_fit(f"set aside: {storage.where(f'{ASIDE}/{directory}')} ({reason})"))
    if any(info.status == INCOMPLETE for info in every) and (holder := saving_now(storage)):
        print(holder)
    if any(info.status == VERIFIED for info in every):  # prune and resume read its digests: they may find it corrupt
        print("committed: by its manifest and file sizes; ftrain ckpt verify (the same URL) reads every byte")
    return 0


def verify(url: str, options: dict | None = None) -> int:
    """Verify every committed step (or the one step) with full digests: 1 if any does not verify, naming each
    failure, else 0. A step without a manifest was never committed (a save cut short): it is told with its age,
    and fails nothing (``resume`` skips it, retention deletes it), unless it is the one step named (1). A run's
    storage must also hold one history (``lineage.py``): superseded steps are named, a fork is named and fails (1).
    A step set aside under ``quarantine/`` is verified where it lies (``_verify_aside``)."""
    if (aside := set_aside_location(url)) is not None:
        return _verify_aside(Storage.open(aside[0], options), aside[1])
    storage, step = _open(url, options)
    progress = Progress()
    progress.show("ckpt verify: reading the steps' manifests...")
    infos = [info for info in scan(storage) if step is None or info.step == step]
    progress.clear()
    committed = [info.step for info in infos if info.status != INCOMPLETE]
    failed, deleted = verify_each(storage, infos)
    past = history(infos) if step is None else None
    if past is not None:
        for info in infos:
            if info.step in past.superseded:
                print(f"step {info.step}: {superseded_reason(info, past)}")
        if past.forks:
            print(f"FORKED: {past.fork_message(storage.url)}")
        else:
            line = f"{counted(len(past.line), 'step')} on one line of descent, {len(past.superseded)} superseded"
            print(f"one history: {line}")
    incomplete = len(infos) - len(committed)
    if incomplete and (holder := saving_now(storage)):
        print(holder)
    never = f"; {incomplete} incomplete (never committed)" if incomplete else ""
    gone = f"; {deleted} deleted meanwhile" if deleted else ""
    checked = len(committed) - deleted
    print(f"{checked - failed} of {counted(checked, 'committed step')} verified{never}{gone}")
    uncommitted = step is not None and checked == 0  # the step named is not committed: ``verify STEP && use STEP``
    return 1 if failed or uncommitted or (past is not None and past.forks) else 0


def verify_each(storage: Storage, infos: list[StepInfo], noun: str = "step", top: str = CHECKPOINTS) -> tuple[int, int]:
    """``verify``'s line for each of ``infos``: a committed step checked with full digests, its problems named under
    ``top`` (the directory of the steps), a step without a manifest told with its age; how many failed, and how many
    were deleted while they were checked (their manifest gone since the listing: a live run's retention, a prune),
    which is no failure. Policy snapshots (``noun``, ``top``) are verified alike, through ftrain.policy.snapshots'
    view of ``policies/``."""
    progress, committed, failed, deleted = Progress(), [info.step for info in infos if info.status != INCOMPLETE], 0, 0
    for info in infos:
        if info.status == INCOMPLETE:
            age = _age(storage.modified(step_dir(info.step)))
            print(f"{noun} {info.step}: incomplete (never committed: no manifest; last written {age})")
            continue
        done = committed.index(info.step)
        progress.count(
            "ckpt verify", done, len(committed), f"{noun}s", f" ({noun} {info.step}: {human_size(info.size)})"
        )
        result = verify_step(storage, info.step, full=True)
        progress.clear()
        if not result.ok and MANIFEST not in storage.list_files(step_dir(info.step)):
            print(f"{noun} {info.step}: deleted while it was checked (a live run's retention, or a prune)")
            deleted += 1
            continue
        print(f"{noun} {info.step}: {'ok' if result.ok else 'FAILED'}")
        for problem in result.problems:
            print(f"  {top}/{step_dir(info.step).partition('/')[2]}/{problem}")
        failed += not result.ok
    return failed, deleted


def _verify_aside(storage: Storage, directory: str) -> int:
    """A step set aside, verified with full digests where it lies, nothing moved: a repair is checked before
    ``unquarantine``, which also asks whether the step may go back (its place free, the storage's line kept)."""
    directory = _aside(storage, directory)
    where = storage.where(f"{ASIDE}/{directory}")
    result = verify_step(storage, aside_step(directory), full=True, directory=f"{ASIDE}/{directory}")
    print(f"{where}: {'ok' if result.ok else 'FAILED'}")
    for problem in result.problems:
        print(f"  {problem}")
    if result.ok:
        print(f"to put it back: {command('ftrain', 'ckpt', 'unquarantine', where)}")
    return 0 if result.ok else 1


def show(url: str, options: dict | None = None, as_json: bool = False) -> int:
    """The manifest of one step, or of the newest verified step under a run's storage."""
    storage, step = _open(url, options)
    if step is None:
        selected = select_resume(storage, log=lambda line: print(line, file=sys.stderr), quarantine_bad=False)
        if selected is None:
            raise UserError(f"no verified checkpoint under {storage.url}: see {_ls(storage)}")
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
                print(f"  {name:<20} {human_size(entry['size']):>9}  sha256 {entry['sha256']}")
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
    keep_last: int | None = None,
    keep_best: int | None = None,
    best_metric: str | None = None,
    keep_every: int | None = None,
    pinned: Iterable[int] = (),
    dry_run: bool = False,
    options: dict | None = None,
    drop_bad: bool = False,
    force: bool = False,
) -> int:
    """Apply the retention rules of ``checkpoint.retention_plan`` to a run's storage (``dry_run``: only print), as the
    holder of its lease (``as_lease_holder``; ``force``: without it). A rule left None is the run's own (the
    ``checkpoint`` settings of its newest verified step, as ``ls`` marks them); ``pinned`` adds to the run's."""
    for name, value, least in (("keep-last", keep_last, 1), ("keep-best", keep_best, 0), ("keep-every", keep_every, 0)):
        if value is not None and value < least:  # the newest verified step is always kept, as checkpoint.keep_last
            raise UserError(f"--{name}={value} must be {'at least 1' if least else '0 or more'}")
    if bad := [step for step in pinned if step < 0]:
        raise UserError(f"--pin {bad[0]} is no step: pin a step of the storage (ftrain ckpt ls names them)")
    storage, step = _open(url, options, one_step=False)
    if step is not None:
        raise UserError(f"prune works on a run's storage, not one step: pass {storage.url}")
    rules = (keep_last, keep_best, best_metric, keep_every, pinned, drop_bad)
    return as_lease_holder(storage, "prune", force, lambda held: _prune(held, *rules, dry_run=dry_run), dry_run)


def keep_line(url: str, step: int, options: dict | None = None, force: bool = False, dry_run: bool = False) -> int:
    """Keep the line of descent that ends at ``step`` (``lineage.py``): every verified step off it is set aside under
    ``quarantine/`` (nothing is deleted), so that the storage holds one history again (``dry_run``: only print). A
    ``step`` that newer steps descend from ends no line: refused, or its own line's newer steps would go aside."""
    storage, _ = _open(url, options, one_step=False)

    def body(held: Storage) -> int:
        infos = scan(held)
        past = history(infos, head=step)
        _refuse_an_inner_step(held, infos, step, past.off_line())
        for info in infos:
            if info.step not in past.off_line():
                continue
            if dry_run:
                print(f"would set aside step {info.step}")
                continue
            quarantine(held, info.step, f"off the line kept by ftrain ckpt prune --keep-line {step}")
            print(f"step {info.step}: set aside to {set_aside(held, info)}")
        done = "would set aside" if dry_run else "set aside"
        kept = "would keep" if dry_run else "kept"
        print(f"{kept} the line of step {step}: {counted(len(past.line), 'step')}; {len(past.off_line())} {done}")
        return 0

    return as_lease_holder(storage, "prune --keep-line", force, body, dry_run)


def _refuse_an_inner_step(storage: Storage, infos: list[StepInfo], step: int, off_line: list[int]) -> None:
    """UserError where newer steps descend from ``step``, naming the ends of their lines (newest generation first) and
    how to train on from ``step`` itself: in another storage, which ``resume=`` hands it to."""
    lines = {info.step: history(infos, head=info.step).line for info in infos if info.step in off_line}
    later = [other for other, line in lines.items() if step in line]
    if not later:
        return
    ends = [end for end in later if not any(end in lines[other] for other in later if other != end)]
    by_generation = {info.step: (generation(info), info.step) for info in infos}
    ends.sort(key=by_generation.get, reverse=True)
    keep = " or ".join(f"--keep-line {end}" for end in ends)
    verb = "descends" if len(later) == 1 else "descend"
    raise UserError(
        f"step {step} does not end a line of descent: {listed_steps(later)} {verb} from it; keep a line that ends "
        f"there ({keep}), or train on from step {step} in another storage: --storage NEW "
        f"resume={storage.where(step_dir(step))}"
    )


def as_lease_holder(
    storage: Storage, command: str, force: bool | None, body: Callable[[Storage], int], dry_run: bool = False
) -> int:
    """``body`` of the storage, with this command holding the storage's lease (``lease.py``) meanwhile: no run starts
    while it deletes, and each of its writes is checked (``fence.guarded``). Refused in one line, with
    ``EXIT_STORAGE_HELD``, while another process holds it; ``force``: without the lease (None: a command that has no
    ``--force``). ``dry_run``: a ``body`` that only prints, without taking the lease; where the command would be
    refused (another run holds the lease), it previews all the same, then says so and exits as the command would (a
    damaged lease is a UserError)."""
    if force:
        return body(storage)
    anyway = f" (or pass --force to {command} anyway)" if force is not None else ""

    def refused(line: str, now: str = "refused") -> None:
        print(f"ftrain: error: ckpt {command} {now}: {line}{anyway}", file=sys.stderr)

    lease = Lease(storage, f"ftrain-ckpt-{secrets.token_hex(4)}", lambda line: print(line, file=sys.stderr))
    if dry_run:
        try:
            lease.check()
        except LeaseHeld as held:
            body(storage)  # what it would do once the storage is free: the preview asked for
            refused(str(held), "would be refused now")
            return EXIT_STORAGE_HELD
        except (OSError, StorageError):  # the storage's clock asks for a write (a read-only mount): the prune tells
            pass
        return body(storage)
    return lease.run(lambda held: body(guarded(storage)), refused)


def _prune(
    storage: Storage,
    keep_last: int | None,
    keep_best: int | None,
    best_metric: str | None,
    keep_every: int | None,
    pinned: Iterable[int],
    drop_bad: bool,
    dry_run: bool,
) -> int:
    """``prune``'s work, as the lease's holder (or with ``dry_run``); a rule left None is the run's own."""
    infos = scan(storage, full=True)  # digests too: a bit-rotted step must not pass for the newest good one
    own = _settings([info for info in infos if info.status == VERIFIED])
    recorded = sorted({name for info in infos if info.status == VERIFIED for name in _metrics(info)})
    if best_metric is not None and recorded and best_metric not in recorded:
        raise UserError(
            f"--best-metric {best_metric}: no step of {storage.url} records it{did_you_mean(best_metric, recorded)}; "
            f"use one of {', '.join(recorded)}"
        )
    if missing := sorted(set(pinned) - {info.step for info in infos}):
        raise UserError(f"--pin {missing[0]}: {storage.url} holds no step {missing[0]}; see {_ls(storage)}")
    keep_last = own.keep_last if keep_last is None else keep_last
    keep_best = own.keep_best if keep_best is None else keep_best
    best_metric = own.best_metric if best_metric is None else best_metric
    keep_every = own.keep_every if keep_every is None else keep_every
    pinned = sorted({*pinned, *own.pinned})
    rules = f"keep_last={keep_last}, keep_best={keep_best} ({best_metric}), keep_every={keep_every}, pinned={pinned}"
    print(f"retention: {rules}")
    doomed = set(retention_plan(infos, keep_last, keep_best, best_metric, keep_every, pinned, drop_bad))
    for info in infos:
        if info.step in doomed and info.status == INCOMPLETE and not abandoned(storage, info, time.time()):
            written = _age(storage.modified(step_dir(info.step)))
            print(f"keeping step {info.step} (incomplete, last written {written}: maybe a save in flight)")
            doomed.discard(info.step)
        elif info.step in doomed:
            why = {VERIFIED: "committed, outside retention", INCOMPLETE: "abandoned, never committed"}.get(
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
    kept = [info for info in infos if info.step not in doomed]
    good = [str(info.step) for info in kept if info.status == VERIFIED]
    line = f"{'would keep' if dry_run else 'kept'} {counted(len(good), 'committed step')}: "
    line += ", ".join(good) or "-"
    for status in (INCOMPLETE, CORRUPT, QUARANTINE):
        if steps := [str(info.step) for info in kept if info.status == status]:
            fix = " (maybe a save in flight)" if status == INCOMPLETE else " (--drop-bad deletes these)"
            line += f"; {len(steps)} {status} left: {', '.join(steps)}{fix}"
    print(line)
    return 0


def unquarantine(url: str, options: dict | None = None) -> int:
    """Lift the quarantine of one step if all its files verify (full digests): 0 if lifted, 1 if it does not
    verify (the step stays quarantined). A step set aside under ``quarantine/`` goes back to ``checkpoints/`` where
    it may (``steps.reinstate``). As the holder of the storage's lease (``as_lease_holder``)."""
    if (aside := set_aside_location(url)) is not None:
        root, directory = aside
        storage = Storage.open(root, options)
        return as_lease_holder(storage, "unquarantine", None, lambda held: _reinstate(held, directory))
    storage, step = _open(url, options)
    if step is None:
        raise UserError(
            f"unquarantine works on one step: pass {storage.url}/{CHECKPOINTS}/step-<N> (see ftrain ckpt ls)"
        )
    return as_lease_holder(storage, "unquarantine", None, lambda held: _unquarantine(held, step))


def _unquarantine(storage: Storage, step: int) -> int:
    info = next(info for info in scan(storage) if info.step == step)
    if info.status != QUARANTINE:
        raise UserError(f"{storage.where(step_dir(step))} is {shown(info.status)}, not quarantined: nothing to lift")
    done = f"verifies: quarantine lifted (was: {info.problems[0].reason})"
    return _told(unquarantine_step(storage, step), storage.where(step_dir(step)), "stays quarantined", done)


def _reinstate(storage: Storage, directory: str) -> int:
    directory = _aside(storage, directory)
    where = storage.where(f"{ASIDE}/{directory}")
    result = reinstate(storage, directory)
    done = f"verifies and continues the storage's line: back at {storage.where(step_dir(result.step))}"
    return _told(result, where, "stays set aside", done)


def _aside(storage: Storage, directory: str) -> str:
    """The name under ``quarantine/`` of the step set aside as ``directory``, its number written short or in full
    (``step-4`` is ``step-000000004``, as in ``checkpoints/``); UserError if it is not there."""
    again = directory.partition(".")[2]
    full = f"step-{aside_step(directory):09d}{'.' * bool(again)}{again}"
    if full not in storage.list_dirs(ASIDE):
        raise UserError(f"{storage.where(f'{ASIDE}/{directory}')} does not exist: see {_ls(storage)}")
    return full


def _ls(storage: Storage) -> str:
    return command("ftrain", "ckpt", "ls", storage.url)


def _told(result: Verification, where: str, stays: str, done: str) -> int:
    """``unquarantine``'s outcome for a step at ``where``: 0 and ``done``, or 1 and why it ``stays``."""
    if result.ok:
        print(f"{where} {done}")
        return 0
    print(f"{where} {stays}: it does not verify")
    for problem in result.problems:
        print(f"  {problem}")
    return 1


def _open(url: str, options: dict | None, one_step: bool = True) -> tuple[Storage, int | None]:
    """The storage and, for the URL of one step, the step; UserError if no checkpoint is there (``one_step``: the
    command takes one step too, and the line says so)."""
    root, step = parse_checkpoint_url(url)
    storage = Storage.open(root, options)
    if step is None and not storage.list_dirs(CHECKPOINTS):
        usual = f"pass a run's storage (the directory holding {CHECKPOINTS}/){' or one step directory' * one_step}"
        check_exists(storage, usual)
        if storage.fs.isfile(storage.root):  # an exported policy, a manifest
            raise UserError(f"{storage.url} is a file: {usual}")
        if LEASE in storage.list_files(""):  # a run's storage all the same
            raise UserError(f"no checkpoints under {storage.url} yet: the run that took it has saved none so far")
        raise UserError(f"no checkpoints under {storage.url}: {part_of_a_storage(storage) or usual}")
    if step is not None:
        step_files(storage, step)
    return storage, step


def _marks(infos: list[StepInfo]) -> dict[int, list[Kept]]:
    """Which verified steps retention keeps and why, by the run's own settings (``_settings``)."""
    verified = [info for info in infos if info.status == VERIFIED]
    settings = _settings(verified)
    return kept(
        verified, settings.keep_last, settings.keep_best, settings.best_metric, settings.keep_every, settings.pinned
    )


def _settings(verified: list[StepInfo]) -> CheckpointConfig:
    """The ``checkpoint`` settings of the newest verified step's run (newest first; the defaults where its manifest
    has none)."""
    recorded = ((verified[0].manifest or {}).get("config") or {}).get("checkpoint") or {} if verified else {}
    return CheckpointConfig(**{k: v for k, v in recorded.items() if k in vars(CheckpointConfig())})


def _metrics(info: StepInfo) -> dict:
    """The metrics ``info``'s manifest records (none: {})."""
    return (info.manifest or {}).get("metrics") or {}


def _fit(line: str) -> str:
    return line if len(line) <= WIDTH else line[: WIDTH - 3] + "..."


def _age(modified: float | None) -> str:
    if modified is None:
        return "at an unknown time"
    seconds = max(0.0, time.time() - modified)
    for unit, size in (("day", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            count = int(seconds // size)
            return f"{count} {unit}{'s' * (unit == 'day' and count != 1)} ago"
    return f"{seconds:.0f} s ago"


def _number(value: object) -> str:
    """A metric for the table: a dash where there is none (not measured, or not recorded)."""
    return f"{value:,.2f}" if is_number(value) else "-"
