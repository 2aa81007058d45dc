"""What is in a storage: the state of every step, resume selection, quarantine, and clearing for a new save.

Rules (see ``format.py`` for what "verified" means): a committed step that fails verification (a missing or
damaged file) is quarantined, never loaded, and never deleted except by an explicit ``ftrain ckpt prune
--drop-bad``; a run that needs its step number again sets it aside under ``quarantine/`` (``reinstate`` puts it
back where it still continues the storage's line). An incomplete step (no manifest) was abandoned and may be
deleted. A step that verifies is never quarantined. No storage lies inside another storage's step directories,
which its retention deletes (``check_storage_place``); a URL of a storage's part that holds no step is told what
to pass instead (``part_of_a_storage``).
"""

from __future__ import annotations

import json
import os
import re
import time
from collections.abc import Callable
from pathlib import Path

from ftrain.ckpt.format import (
    CANONICAL_STEP_DIR,
    CHECKPOINTS,
    CORRUPT,
    INCOMPLETE,
    MANIFEST,
    POLICIES,
    QUARANTINE,
    QUARANTINED,
    STEP_DIR,
    VERIFIED,
    CorruptCheckpoint,
    Problem,
    StepInfo,
    Verification,
    content_problem,
    now,
    parse_checkpoint_url,
    read_manifest,
    spellings,
    step_dir,
    verify_listed,
    verify_step,
)
from ftrain.ckpt.lease import saving_now
from ftrain.ckpt.lineage import History, generation, history
from ftrain.ckpt.retention import delete_step
from ftrain.ckpt.storage import Storage
from ftrain.config import blocking_file, check_writable, local_path
from ftrain.errors import UserError, command
from ftrain.redact import display_url

ASIDE = "quarantine"
"""Where corrupt and quarantined steps go when a run needs their step number again (see :func:`set_aside`)."""


STEP_PARENTS = (CHECKPOINTS, ASIDE, POLICIES)
"""The directories of a storage whose ``step-N`` (``step-N.k`` set aside again) its run's retention deletes."""
_STEP_NAME = re.compile(r"^step-\d+(\.\d+)?$")


def _enclosing_step(url: str) -> tuple[str, str, str] | None:
    """The step directory of a storage that ``url`` is or lies inside, its parent's name (``STEP_PARENTS``) and the
    storage's root; None where there is none, or where the parent is a bucket (nothing can lie above a bucket)."""
    parts = url.partition("?")[0].rstrip("/").split("/")
    for index in range(1, len(parts)):
        if _STEP_NAME.match(parts[index]) and parts[index - 1] in STEP_PARENTS:
            above = parts[: index - 1]
            root = "/".join(above) or ("/" if above else ".")
            if not root.endswith(":/"):
                return "/".join(parts[: index + 1]), parts[index - 1], root
    return None


def check_not_a_checkpoints_directory(storage: Storage) -> None:
    """UserError if ``storage`` holds step directories itself: it is the ``checkpoints/`` of a run (``--storage
    <run>/checkpoints``), where a run would start fresh beside that run's steps."""
    if steps := sorted(name for name in storage.list_dirs("") if CANONICAL_STEP_DIR.match(name)):
        raise UserError(
            f"storage {storage.url} holds step directories itself ({', '.join(steps[-2:])}): it is the {CHECKPOINTS} "
            "directory of a run, whose storage is the directory above it: pass that to resume it, or a directory "
            "of its own"
        )


def check_storage_place(url: str) -> None:
    """UserError if ``url`` is or lies inside a step directory of a storage (``<run>/checkpoints/step-N``, one set
    aside under ``quarantine/``, a policy snapshot under ``policies/``) or a storage's ``quarantine/``: that run's
    retention and clean-up would delete what a run there writes."""
    shown = display_url(url)
    if (found := _enclosing_step_of_any(shown)) is None:
        if (run := _quarantine_around(url)) is not None:
            raise UserError(
                f"storage {shown} is the {ASIDE}/ of the run in {run}, or lies inside it: ftrain ckpt prune "
                "--drop-bad deletes all of it: pass a directory of its own"
            )
        return
    where, step, parent = found
    resume = f" (to train on from that step: resume={step})" if parent == CHECKPOINTS else ""
    if resume and (local := local_path(step)) and not os.path.isdir(local):  # no step to train on from
        listing = command("ftrain", "ckpt", "ls", os.path.dirname(os.path.dirname(local)) or ".")
        resume = f" ({step} does not exist; its steps: {listing})"
    place = "is" if step == where.partition("?")[0].rstrip("/") else f"is inside {step},"
    raise UserError(
        f"storage {shown} {place} a step of another run's storage, which that run may delete: pass a directory of "
        f"its own{resume}"
    )


def check_steps_place(storage: str) -> None:
    """UserError where a local storage's ``checkpoints/`` is a file, or holds a symbolic link named as ftrain names a
    step: every save would fail until someone moves the file (a run held for an hour), or write through the link,
    outside the storage, into a step that listings do not see."""
    path = os.path.join(storage, CHECKPOINTS)
    if (blocking := blocking_file(path)) is not None:
        raise UserError(f"cannot write {path}: {blocking} is a file where ftrain needs a directory: move it away")
    try:
        entries = list(os.scandir(path)) if os.path.isdir(path) else []
    except PermissionError as error:
        raise UserError(f"cannot read {path} ({error.strerror}): make it readable, or pass --storage another") from None
    except OSError:  # a storage that fails (EIO, a link to itself): its listing says so, as an outage
        return
    if links := sorted(e.name for e in entries if e.is_symlink() and CANONICAL_STEP_DIR.match(e.name)):
        raise UserError(
            f"{os.path.join(path, links[0])} is a symbolic link, where ftrain writes and deletes steps of its own: "
            f"move it out of {path}"
        )


def check_output(path: Path, option: str) -> None:
    """UserError unless the file a command writes (``option``: the flag that chose ``path``) can be written and lies
    outside every step directory of a storage (``check_outside_steps``)."""
    check_outside_steps(path, option)
    check_writable(path, option)


def check_outside_steps(path: Path, option: str) -> None:
    """UserError if ``path`` (``option``: the flag or key that chose it) lies inside a step directory of a storage,
    or its ``quarantine/``: there a file would replace a committed one of the same name (``export -o
    .../common.pt``) or go when retention deletes the step."""
    if (found := _enclosing_step_of_any(str(path))) is not None:
        raise UserError(
            f"{option} {path} lies inside {found[1]}, a step of a run's storage: a file written there replaces the "
            f"step's own or is deleted with it: pass {option} a path outside the storage's steps"
        )
    if (run := _quarantine_around(str(path))) is not None:
        raise UserError(
            f"{option} {path} lies inside the {ASIDE}/ of the run in {run}: ftrain ckpt prune --drop-bad deletes "
            f"all of it: pass {option} a path outside it"
        )


def _quarantine_around(url: str) -> str | None:
    """The local storage whose ``quarantine/`` ``url`` is or lies inside (a directory there is a step set aside,
    whatever its name, which ``prune --drop-bad`` deletes), or None: the first place so named that is a run's storage
    (it holds ``checkpoints/``), by the path as written (``..`` resolved) and where it really goes."""
    if not (local := local_path(url)):
        return None
    for where in dict.fromkeys((os.path.normpath(os.path.abspath(local)), os.path.realpath(local))):
        parts = where.split("/")
        for index in range(2, len(parts)):
            root = "/".join(parts[:index])
            if parts[index] == ASIDE and os.path.isdir(os.path.join(root, CHECKPOINTS)):
                return root
    return None


def _enclosing_step_of_any(url: str) -> tuple[str, str, str] | None:
    """The first spelling of ``url`` (``format.spellings``) that lies inside a step directory, that step and its
    parent's name; None where no spelling does."""
    for where in spellings(url):
        if (found := _enclosing_step(where)) is not None:
            return where, found[0], found[1]
    return None


def scan(storage: Storage, full: bool = False) -> list[StepInfo]:
    """Every step directory, newest first. ``full`` checks digests too (reads every file); else sizes only."""
    infos = []
    for name in storage.list_dirs(CHECKPOINTS):
        match = CANONICAL_STEP_DIR.match(name)
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
        status = VERIFIED if result.ok else INCOMPLETE if result.never_committed else CORRUPT
        strays = bool(result.manifest) and bool(present.keys() - result.manifest["files"].keys() - {MANIFEST})
        infos.append(StepInfo(step, status, size, result.manifest, result.problems, strays))
    return sorted(infos, key=lambda info: info.step, reverse=True)


def quarantine(storage: Storage, step: int, reason: str) -> None:
    """Mark ``step`` as never to be loaded again; its data stays for a human to inspect."""
    marker = {"step": step, "reason": reason, "time": now()}
    storage.write_replace(f"{step_dir(step)}/{QUARANTINED}", (json.dumps(marker, indent=2) + "\n").encode())


def unquarantine(storage: Storage, step: int) -> Verification:
    """Lift the quarantine of ``step`` if every file verifies against its manifest (full digests); the verification
    either way (the marker stays unless it is ok)."""
    result = verify_step(storage, step, full=True)
    if result.ok:
        storage.delete(f"{step_dir(step)}/{QUARANTINED}")
    return result


def select_resume(
    storage: Storage, log: Callable[[str], None] = print, quarantine_bad: bool = True
) -> tuple[int, dict] | None:
    """The newest step that fully verifies, with its manifest; None if there is none.

    Only steps on the storage's line of descent count (``lineage.history``): a superseded step is passed over; a fork
    is a UserError where the storage is this run's own (``quarantine_bad``), else the head's line is read. Each newer
    step that is skipped is reported through ``log`` with the reason; a committed step that fails verification is
    quarantined (unless ``quarantine_bad`` is False, e.g. for someone else's read-only run).
    """
    infos = scan(storage)
    past = history(infos)
    if past.forks and quarantine_bad:  # this run's own storage: it must not go on from one of two histories
        raise UserError(past.fork_message(storage.url))
    if past.forks:  # someone else's, read only (play, export, a teacher): the head's line, said
        log(f"{storage.url} holds two histories: reading the newest one's line (steps {past.line[:3]}...)")
    forks = set(past.forks)
    reading = not quarantine_bad and any(info.status == INCOMPLETE for info in infos)
    in_flight = saving_now(storage) if reading else None  # else "incomplete" reads as a save cut short
    for info in infos:
        if info.step in past.superseded:
            log(f"skipping checkpoint step {info.step}: {superseded_reason(info, past)}")
            continue
        if info.step in forks:
            log(f"skipping checkpoint step {info.step}: off the newest history's line")
            continue
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
            why = in_flight if status == INCOMPLETE and in_flight else reasons
            log(f"skipping checkpoint step {info.step}: {status} ({why})")
    return None


def clear_newer(storage: Storage, step: int, log: Callable[[str], None] = print) -> None:
    """Prepare a run starting from ``step`` (0 for a fresh start) to save the following steps again.

    Every save needs a fresh directory. Incomplete steps newer than ``step`` were abandoned by the run that died
    (never committed: ``scan`` looks at the manifest itself): they are deleted, since the attempt that wrote them is
    dead on this node (``Attempt.kill`` waits for it) and fenced off on others. Where a listing may lag
    (``Storage.lists_late``: NFS), a manifest another host wrote seconds ago may be missing from it and even from a
    direct look, so only a step untouched for ``ABANDONED_AFTER`` seconds is deleted; a younger one is set aside
    whole. Corrupt, quarantined and superseded ones (``lineage.py``; superseded ones older than ``step`` too) are set
    aside (:func:`set_aside`), never deleted.
    Another verified newer step means the storage holds another history: UserError, nothing touched. Call it on rank 0
    before the first save, when no other process writes to this storage.
    """
    infos = scan(storage)
    past = history(infos)
    superseded = past.superseded
    newer = [info for info in infos if info.step > step]
    verified = [info.step for info in newer if info.status == VERIFIED and info.step not in superseded]
    if verified:
        raise UserError(
            f"{storage.url} already holds verified checkpoint step {verified[0]}, newer than step {step} this run "
            "starts from: resume from the newest step or use another storage"
        )
    older = [info for info in infos if info.step <= step and info.step in superseded]  # out of retention's counts too
    for info in [*newer, *older]:
        young = info.status == INCOMPLETE and storage.lists_late and not abandoned(storage, info, time.time())
        if info.status == INCOMPLETE and not young:
            log(f"deleting checkpoint step {info.step} (incomplete): newer than step {step} this run starts from")
            delete_step(storage, info.step)
            continue
        status = info.status
        if info.step in superseded:
            status = "superseded"
            quarantine(storage, info.step, superseded_reason(info, past))
        if young:
            ago = time.time() - (storage.modified(step_dir(info.step)) or time.time())
            status = f"incomplete, last written {ago:.0f} s ago"
            reason = f"{status} on a file system whose listings may lag: set aside, not deleted"
            quarantine(storage, info.step, reason)
        where = set_aside(storage, info)
        newer_than = f": newer than step {step}, which this run goes on from" if info.step > step else ""
        log(f"checkpoint step {info.step} ({status}) moved to {where}{newer_than}")


ABANDONED_AFTER = 600.0
"""Seconds since a step without a manifest was last written before ``ftrain ckpt prune`` takes it for abandoned:
a younger one may be a save in flight, of a run on another host."""


def abandoned(storage: Storage, info: StepInfo, now: float) -> bool:
    """Whether an incomplete step (no manifest, looked at directly: see ``format.verify_listed``) may be deleted by
    a cleanup that does not know who writes to the storage: nothing written for ``ABANDONED_AFTER`` seconds (the
    storage's times against ``now``, this machine's)."""
    written = storage.modified(step_dir(info.step))
    return info.status == INCOMPLETE and (written is None or now - written >= ABANDONED_AFTER)


def set_aside(storage: Storage, info: StepInfo) -> str:
    """Move a corrupt or quarantined step out of ``checkpoints/`` into ``quarantine/`` (quarantining it first if it
    is merely corrupt), so that a run can save that step number again; its printable new URL. Every file is copied
    before the original directory goes, so nothing is lost if this fails halfway. Only ``ftrain ckpt prune
    --drop-bad`` deletes what lies there."""
    if info.status == CORRUPT:
        quarantine(storage, info.step, "; ".join(str(problem) for problem in info.problems))
    names = storage.list_files(step_dir(info.step))
    taken = set(storage.list_dirs(ASIDE))
    target = next(f"{ASIDE}/{name}" for n in range(len(taken) + 1) if (name := _aside_name(info.step, n)) not in taken)
    for name in names:
        storage.write_exclusive(f"{target}/{name}", storage.read(f"{step_dir(info.step)}/{name}"))
    storage.delete_tree(step_dir(info.step))
    return storage.where(target)


def aside_step(directory: str) -> int:
    """The step number of a directory set aside under ``quarantine/`` (``step-000000120``, or ``.2`` after it)."""
    return int(STEP_DIR.match(directory.split(".")[0])[1])


def reinstate(storage: Storage, directory: str) -> Verification:
    """Move a step set aside (``quarantine/<directory>``) back to its place under ``checkpoints/`` if every file it
    lists verifies (full digests), its number is free there, and the storage's history with it keeps its line and
    gains no step off it (``lineage.py``: a step the run went on without, or one of a line a person set aside with
    ``--keep-line``, stays aside). UserError where it may not go back; its verification otherwise. Each file is
    checked as it is copied, the manifest last (it commits the step; a file that does not verify: the copy goes,
    nothing committed), then the set-aside step goes."""
    step, source = aside_step(directory), f"{ASIDE}/{directory}"
    result = verify_step(storage, step, full=False, directory=source)  # the digests: as each file is copied
    if result.never_committed:
        raise UserError(f"{storage.where(source)} has no manifest (never committed): nothing to reinstate")
    if not result.ok:
        return result
    if MANIFEST in (present := storage.list_files(step_dir(step))):
        raise UserError(
            f"{storage.where(source)} cannot go back: {storage.where(step_dir(step))} holds the run's own step {step} "
            "now, committed after it was set aside"
        )
    if present:
        raise UserError(
            f"{storage.where(source)} cannot go back: {storage.where(step_dir(step))} holds files of a step never "
            f"committed (a save or a copy cut short): {command('ftrain', 'ckpt', 'prune', storage.url)} deletes "
            "it once abandoned"
        )
    infos = scan(storage)
    before, after = history(infos), history([*infos, StepInfo(step, VERIFIED, 0, result.manifest)])
    if step not in after.line or not set(before.line) <= set(after.line) or after.forks != before.forks:
        line = ", ".join(map(str, before.line[:3])) + (" ..." if len(before.line) > 3 else "")
        raise UserError(
            f"{storage.where(source)} cannot go back: it does not continue the storage's line of descent (steps "
            f"{line or 'none'}), so resume would set it aside again"
        )
    for name, entry in result.manifest["files"].items():
        data = storage.read(f"{source}/{name}")
        if (problem := content_problem(name, data, entry)) is not None:
            result.problems.append(problem)
        else:
            storage.write_exclusive(f"{step_dir(step)}/{name}", data)
    if not result.ok:  # never committed: what was copied goes
        storage.delete_tree(step_dir(step))
        return result
    storage.write_exclusive(f"{step_dir(step)}/{MANIFEST}", storage.read(f"{source}/{MANIFEST}"), commit=True)
    storage.delete_tree(source)
    return result


def set_aside_steps(storage: Storage) -> list[tuple[str, str]]:
    """``(directory, quarantine reason)`` of every step set aside under ``quarantine/``."""
    return [(name, _quarantine_reason(storage, name, ASIDE)) for name in storage.list_dirs(ASIDE)]


def _aside_name(step: int, n: int) -> str:
    return f"step-{step:09d}" + (f".{n}" if n else "")


def part_of_a_storage(storage: Storage) -> str | None:
    """What to pass instead of ``storage``, which holds no step: where it is a run's ``checkpoints/`` directory (its
    listing holds steps), a step set aside under ``quarantine/`` or a policy snapshot, the line that refuses it says
    so; else None."""
    for where in spellings(storage.url):  # as given, then where a local path really is (``.`` in checkpoints/)
        head, _, last = where.rstrip("/").rpartition("/")
        parent = head or ("/" if where.startswith("/") else ".")
        above_a_bucket = parent.endswith(":/")  # nothing can lie above a bucket
        if last == CHECKPOINTS and not above_a_bucket and any(map(CANONICAL_STEP_DIR.match, storage.list_dirs(""))):
            return f"that is the {CHECKPOINTS}/ directory of {parent}: pass {parent}"
        if _STEP_NAME.match(last) and head.rpartition("/")[2] == POLICIES:
            run = head.rpartition("/")[0] or "."
            return f"that is a policy snapshot of {run} (ftrain play and export take it): pass {run} for checkpoints"
        if (found := _enclosing_step(where)) is not None and found[1] == ASIDE:
            ls, back = command("ftrain", "ckpt", "ls", found[2]), command("ftrain", "ckpt", "unquarantine", found[0])
            return (
                f"that is a step set aside under {ASIDE}/, out of the history of {found[2]}: see {ls}; {back} puts "
                "it back if it may go back"
            )
    return None


def set_aside_location(url: str) -> tuple[str, str] | None:
    """``(storage root, directory under quarantine/)`` where ``url`` is a step set aside; else None."""
    for spelt in spellings(url):
        found = _enclosing_step(spelt)
        if found is not None and found[1] == ASIDE and found[0] == spelt.partition("?")[0].rstrip("/"):
            return found[2], found[0].rpartition("/")[2]
    return None


def check_exists(storage: Storage, instead: str) -> None:
    """UserError where ``storage`` is a local directory that is not there, with what to pass ``instead``."""
    if storage.is_local and not storage.exists(""):
        raise UserError(f"{storage.url} does not exist: {instead}")


def step_files(storage: Storage, step: int) -> dict[str, int]:
    """The files of ``step``'s directory (name: size); UserError where it is not there: moved to ``quarantine/``,
    deleted, or never there. An empty directory is there (a save that wrote nothing yet, or was cut short at once),
    as ``ls`` lists it: without a manifest."""
    present = storage.list_files(step_dir(step))
    if not present and step_dir(step).rpartition("/")[2] not in storage.list_dirs(CHECKPOINTS):
        ls = command("ftrain", "ckpt", "ls", storage.url)
        raise UserError(f"checkpoint {storage.where(step_dir(step))} does not exist: see {ls}")
    return present


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
            raise _no_checkpoint(storage)
        return storage, *selected
    return storage, step, _named_step(storage, step, full=True)


def check_checkpoint_url(url: str) -> None:
    """UserError where ``resolve_checkpoint_url`` would find nothing at ``url`` (a local one), from listings and the
    manifest alone, without reading the shards: a storage without a step directory, a step whose files do not match
    its manifest or that has none. Before a start that would take a storage and print its banner first."""
    root, step = parse_checkpoint_url(url)
    storage = Storage.open(root)
    if step is not None:
        _named_step(storage, step, full=False)
    elif not any(map(CANONICAL_STEP_DIR.match, storage.list_dirs(CHECKPOINTS))):
        raise _no_checkpoint(storage)


def _named_step(storage: Storage, step: int, full: bool) -> dict:
    """The manifest of ``step``, named by the user; UserError where it does not verify (``full``: its digests too)."""
    result = verify_listed(storage, step, step_files(storage, step), full=full)
    if result.never_committed and (in_flight := saving_now(storage)):
        ls = command("ftrain", "ckpt", "ls", storage.url)
        raise UserError(
            f"checkpoint {storage.where(step_dir(step))} is not committed ({in_flight}): pick a committed step (see "
            f"{ls}), or pass {storage.url} for its newest"
        )
    if not result.ok:
        problems = "; ".join(str(p) for p in result.problems)
        raise UserError(f"checkpoint {storage.where(step_dir(step))} does not verify ({problems}): pick another step")
    return result.manifest


def _no_checkpoint(storage: Storage) -> UserError:
    """Why ``storage`` gives no checkpoint, where none of its steps verifies (or it has none)."""
    check_exists(storage, "pass a run's storage or a step directory")
    steps = storage.list_dirs(CHECKPOINTS)  # none verifies: ls tells why
    ls = f"see {command('ftrain', 'ckpt', 'ls', storage.url)}"
    fix = part_of_a_storage(storage) or (ls if steps else "pass a run's storage or a step directory")
    return UserError(f"no verified checkpoint under {storage.url}: {fix}")


def _quarantine_reason(storage: Storage, step: int | str, parent: str = CHECKPOINTS) -> str:
    directory = step_dir(step) if parent == CHECKPOINTS else f"{parent}/{step}"
    try:
        return str(json.loads(storage.read(f"{directory}/{QUARANTINED}"))["reason"])
    except (FileNotFoundError, ValueError, TypeError, KeyError, RecursionError):
        return "quarantined (marker unreadable)"


def _manifest_or_none(storage: Storage, step: int) -> dict | None:
    try:
        return read_manifest(storage, step)
    except (FileNotFoundError, CorruptCheckpoint):
        return None


def superseded_reason(info: StepInfo, past: History) -> str:
    """Why ``info`` is off ``past``'s line and superseded, in words."""
    return (
        f"superseded: committed by generation {generation(info)[0]} after generation {past.generation[0]} went on from "
        "an earlier step (a commit that landed after its lease had moved on)"
    )
