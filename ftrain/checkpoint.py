"""Checkpoint format: sharded step directories committed by a manifest, verification, resume selection, retention.

Layout under a storage root (see DESIGN.md, "Checkpoint format")::

    checkpoints/step-000000120/{common.pt, rank-00000.pt, ..., MANIFEST.json}

A step is committed when its MANIFEST.json exists; the manifest is written last, with exclusive create, and
lists every file with its size and SHA-256. Verified = the manifest parses and every listed file has its size
and digest. Readers trust nothing else. Single process: the trainer does the collectives around these calls.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import re
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import torch

from ftrain import packing, ptfile
from ftrain.errors import UserError
from ftrain.storage import Storage

FORMAT_VERSION = 1
STATE_FORMAT = 3
"""Layout of the training state inside the files, in every manifest as ``state_format`` (none before 2: one
tensor per sub-env field, unpacked; 3: the sub-envs' PCG64 states in one tensor). Resume refuses a layout not in
``RESUMABLE_STATE_FORMATS``; policies load from any. From 3 on, ``state_sha256`` is :func:`ftrain.packing.digest`
of the packed learned state (dict order counts), and ``common.pt`` holds the config as JSON text; the digests of
format 2 steps were made another way and do not compare with them."""
RESUMABLE_STATE_FORMATS = (2, 3)
CHECKPOINTS = "checkpoints"
MANIFEST = "MANIFEST.json"
QUARANTINED = "QUARANTINED.json"
COMMON = "common.pt"
"""The state every rank shares (models, optimizer, counters, hooks), written once."""
VERIFIED, INCOMPLETE, CORRUPT, QUARANTINE = "verified", "incomplete", "corrupt", "quarantined"

_STEP_DIR = re.compile(r"^step-(\d+)$")
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_RESERVED = {"format_version", "step", "files"}


class CorruptCheckpoint(Exception):
    """A checkpoint file or manifest does not match what was committed, or is not plain data."""


@dataclass(frozen=True)
class FileEntry:
    size: int
    sha256: str


@dataclass(frozen=True)
class Problem:
    file: str
    reason: str

    def __str__(self) -> str:
        return f"{self.file}: {self.reason}"


@dataclass
class Verification:
    step: int
    problems: list[Problem] = field(default_factory=list)
    manifest: dict | None = None
    """The parsed manifest, if it parsed."""

    @property
    def ok(self) -> bool:
        return not self.problems


@dataclass
class StepInfo:
    step: int
    status: str
    """``verified``, ``incomplete`` (no manifest), ``corrupt`` or ``quarantined``."""
    size: int = 0
    """Bytes of all files in the step directory."""
    manifest: dict | None = None
    problems: list[Problem] = field(default_factory=list)
    strays: bool = False
    """Its directory holds files that its manifest does not list (a scan's listing saw them)."""

    @property
    def metrics(self) -> dict:
        return (self.manifest or {}).get("metrics") or {}

    @property
    def files(self) -> list[str]:
        """The files besides the manifest, if all are known: its manifest's list (none with strays or no manifest:
        for :func:`delete_step`, which then deletes the directory's tree)."""
        return [] if self.strays else list((self.manifest or {}).get("files") or {})


def shard_name(rank: int) -> str:
    """The file of what differs per rank (environments, random streams)."""
    return f"rank-{rank:05d}.pt"


def step_dir(step: int) -> str:
    return f"{CHECKPOINTS}/step-{step:09d}"


def parse_checkpoint_url(url: str) -> tuple[str, int | None]:
    """Split the URL of one step (``<root>/checkpoints/step-000000120``) into root and step; else ``(url, None)``."""
    head, _, last = url.rstrip("/").rpartition("/")
    match = _STEP_DIR.match(last)
    if match is None or (head != CHECKPOINTS and not head.endswith("/" + CHECKPOINTS)):
        return url, None
    root = head[: -len(CHECKPOINTS)].rstrip("/") or ("/" if head.startswith("/") else ".")
    return root, int(match[1])


def encode(state: dict) -> bytes:
    """A ``torch.save`` file of ``state``; a packed state's is written by :mod:`ftrain.ptfile`, several times faster."""
    data = ptfile.write(state) if packing.is_packed(state) else None
    if data is not None:
        return data
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def decode(data: bytes, name: str = "checkpoint data") -> dict:
    """Load with ``weights_only=True``: tensors, numbers, strings, lists and dicts; anything else is refused.
    A packed state (see ``packing.py``) comes back unpacked."""
    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:
        raise CorruptCheckpoint(f"{name} is not loadable as plain data: {_load_failure(exc)}") from None
    if not isinstance(state, dict):
        raise CorruptCheckpoint(f"{name} holds a {type(state).__name__}, not a dict")
    if packing.is_packed(state):
        try:
            return packing.unpack(state)
        except ValueError as exc:
            raise CorruptCheckpoint(f"{name}: {exc}") from None
    return state


def write_file(storage: Storage, step: int, name: str, data: bytes) -> FileEntry:
    """Create one file of ``step`` (exclusive: FileExistsError if it exists) and return its manifest entry."""
    _check_name(name)
    storage.write_exclusive(f"{step_dir(step)}/{name}", data)
    return FileEntry(len(data), hashlib.sha256(data).hexdigest())


def commit(storage: Storage, step: int, files: dict[str, FileEntry], meta: dict, check_present: bool = True) -> dict:
    """Commit ``step``: check every file is there with its size (one listing; skipped without ``check_present``),
    then create MANIFEST.json (exclusive, last).

    ``meta`` adds fields to the manifest (iteration, world_size, config, metrics, ...); ``created`` (UTC,
    ISO 8601) is filled in unless given.
    """
    clash = _RESERVED & meta.keys()
    if clash:
        raise ValueError(f"meta must not set {sorted(clash)}: commit writes them")
    for name in files:
        _check_name(name)
    if check_present:
        present = storage.list_files(step_dir(step))
        for name, entry in files.items():
            actual = present.get(name)
            if actual != entry.size:
                found = "missing" if actual is None else f"{actual} bytes"
                raise CorruptCheckpoint(
                    f"cannot commit step {step}: {name} is {found} in storage, {entry.size} expected"
                )
    manifest = {"format_version": FORMAT_VERSION, "step": step, "created": _now()} | meta
    manifest["files"] = {name: {"size": e.size, "sha256": e.sha256} for name, e in sorted(files.items())}
    data = _manifest_text(manifest).encode()
    storage.write_exclusive(f"{step_dir(step)}/{MANIFEST}", data)
    return manifest


def read_manifest(storage: Storage, step: int) -> dict:
    """The manifest of ``step``: FileNotFoundError if there is none, CorruptCheckpoint if it is not valid."""
    data = storage.read(f"{step_dir(step)}/{MANIFEST}")
    try:
        manifest = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptCheckpoint(f"not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise CorruptCheckpoint("not a JSON object")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise CorruptCheckpoint(f"format_version {manifest.get('format_version')!r} is not {FORMAT_VERSION}")
    if manifest.get("step") != step:
        raise CorruptCheckpoint(f"wrong step: says {manifest.get('step')!r}, directory is step {step}")
    files = manifest.get("files")
    if not isinstance(files, dict) or not all(_valid_entry(n, e) for n, e in files.items()):
        raise CorruptCheckpoint("'files' is not a mapping of file name to {size, sha256}")
    return manifest


def verify(storage: Storage, step: int, full: bool = True) -> Verification:
    """Check ``step`` against its manifest: sizes always, SHA-256 digests too when ``full``."""
    return _verify(storage, step, storage.list_files(step_dir(step)), full)


def read_verified(storage: Storage, step: int, name: str, manifest: dict) -> dict:
    """Read one file of ``step``, check its size and SHA-256 against ``manifest``, then decode it."""
    entry = manifest["files"].get(name)
    where = storage.where(f"{step_dir(step)}/{name}")
    if entry is None:
        raise CorruptCheckpoint(f"{where} is not listed in the manifest of step {step}")
    try:
        data = storage.read(f"{step_dir(step)}/{name}")
    except FileNotFoundError:
        raise CorruptCheckpoint(f"{where} is missing") from None
    problem = _content_problem(name, data, entry)
    if problem:
        raise CorruptCheckpoint(f"{where}: {problem.reason}")
    return decode(data, where)


def scan(storage: Storage, full: bool = False) -> list[StepInfo]:
    """Every step directory, newest first. ``full`` checks digests too (reads every file); else sizes only."""
    infos = []
    for name in storage.list_dirs(CHECKPOINTS):
        match = _STEP_DIR.match(name)
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
        result = _verify(storage, step, present, full)
        status = VERIFIED if result.ok else INCOMPLETE if MANIFEST not in present else CORRUPT
        strays = bool(result.manifest) and bool(present.keys() - result.manifest["files"].keys() - {MANIFEST})
        infos.append(StepInfo(step, status, size, result.manifest, result.problems, strays))
    return sorted(infos, key=lambda info: info.step, reverse=True)


def quarantine(storage: Storage, step: int, reason: str) -> None:
    """Mark ``step`` as never to be loaded again; its data stays for a human to inspect."""
    marker = {"step": step, "reason": reason, "time": _now()}
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
            result = verify(storage, info.step, full=True)
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
    result = verify(storage, step)
    if not result.ok:
        problems = "; ".join(str(p) for p in result.problems)
        raise UserError(f"checkpoint {storage.where(step_dir(step))} does not verify ({problems}): pick another step")
    return storage, step, result.manifest


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
    ranked = sorted(
        (info for info in verified if _metric(info, best_metric) is not None), key=lambda i: -_metric(i, best_metric)
    )
    keep = {verified[0].step, *pinned}
    keep |= {info.step for info in verified[:keep_last]} | {info.step for info in ranked[:keep_best]}
    if keep_every > 0:
        keep |= {info.step for info in verified if info.step % keep_every == 0}
    newest = verified[0].step
    deletable = {VERIFIED, INCOMPLETE} | ({CORRUPT, QUARANTINE} if drop_bad else set())
    return [
        info.step
        for info in steps
        if info.status in deletable and info.step not in keep and not (info.status == INCOMPLETE and info.step > newest)
    ]


def delete_step(storage: Storage, step: int, files: Iterable[str] = ()) -> None:
    """Delete the manifest first (the step stops being committed), then the rest: given the names of its other
    ``files`` (its manifest's list), those without a listing (a request less on S3), else the directory's tree."""
    storage.delete(f"{step_dir(step)}/{MANIFEST}")
    files = list(files)
    if not files or not storage.delete_files(step_dir(step), files):
        storage.delete_tree(step_dir(step))


def _verify(storage: Storage, step: int, present: dict[str, int], full: bool) -> Verification:
    result = Verification(step)
    if MANIFEST not in present:
        result.problems.append(Problem(MANIFEST, "missing: the step was never committed"))
        return result
    try:
        result.manifest = read_manifest(storage, step)
    except FileNotFoundError:
        result.problems.append(Problem(MANIFEST, "missing: the step was never committed"))
        return result
    except CorruptCheckpoint as exc:
        result.problems.append(Problem(MANIFEST, f"unusable: {exc}"))
        return result
    for name, entry in result.manifest["files"].items():
        if name not in present:
            result.problems.append(Problem(name, "missing"))
        elif present[name] != entry["size"]:
            result.problems.append(
                Problem(name, f"size mismatch: {present[name]} bytes, manifest says {entry['size']}")
            )
        elif full:
            try:
                problem = _content_problem(name, storage.read(f"{step_dir(step)}/{name}"), entry)
            except FileNotFoundError:
                problem = Problem(name, "missing")
            if problem:
                result.problems.append(problem)
    return result


def _content_problem(name: str, data: bytes, entry: dict) -> Problem | None:
    if len(data) != entry["size"]:
        return Problem(name, f"size mismatch: {len(data)} bytes, manifest says {entry['size']}")
    digest = hashlib.sha256(data).hexdigest()
    if digest != entry["sha256"]:
        return Problem(name, f"sha256 mismatch: {digest[:12]}..., manifest says {entry['sha256'][:12]}...")
    return None


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


def _metric(info: StepInfo, name: str) -> float | None:
    value = info.metrics.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
        return None
    return float(value)


def _check_name(name: str) -> None:
    if not _plain_name(name) or name in (MANIFEST, QUARANTINED):
        raise ValueError(f"{name!r} is not a valid checkpoint file name")


def _plain_name(name: object) -> bool:
    return isinstance(name, str) and name not in ("", ".", "..") and "/" not in name and "\\" not in name


def _valid_entry(name: object, entry: object) -> bool:
    return (
        _plain_name(name)
        and isinstance(entry, dict)
        and isinstance(entry.get("size"), int)
        and entry["size"] >= 0
        and isinstance(entry.get("sha256"), str)
        and _SHA256.match(entry["sha256"]) is not None
    )


def _load_failure(exc: Exception) -> str:
    """The useful line of a torch.load error (the weights_only ones are a page long)."""
    text = str(exc)
    match = re.search(r"WeightsUnpickler error:\s*(.*?)(?: was not an allowed|\.? Please|\n\n|$)", text, re.S)
    reason = match[1] if match else text.split(". ")[0]
    return f"{type(exc).__name__}: {' '.join(reason.split())}"


def _manifest_text(manifest: dict) -> str:
    """One top-level key per line, each value compact: readable, and written by the C encoder (``indent`` would
    take the pure-Python one, a good part of a save's CPU time with the config in the manifest)."""
    lines = (f"  {json.dumps(key)}: {json.dumps(value)}" for key, value in manifest.items())
    return "{\n" + ",\n".join(lines) + "\n}\n"


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
