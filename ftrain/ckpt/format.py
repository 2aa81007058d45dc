"""Checkpoint format: sharded step directories committed by a manifest, and their verification.

Layout under a storage root::

    checkpoints/step-000000120/{common.pt, rank-00000.pt, ..., MANIFEST.json}

A step is committed when its MANIFEST.json exists; the manifest is written last, with exclusive create, and
lists every file with its size and SHA-256, and its own digest. Verified = the manifest parses, matches its own
digest, and every listed file has its size and digest. Readers trust nothing else. Single process: ``manager.py``
does the collectives around these calls; ``steps.py`` looks at whole storages, ``retention.py`` deletes.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import time
from dataclasses import dataclass, field

from ftrain.ckpt.storage import Storage
from ftrain.errors import StorageError, StorageUnavailable
from ftrain.values import is_whole

FORMAT_VERSION = 1
STATE_FORMAT = 4
"""Layout of the training state inside the files, in every manifest as ``state_format``. 4: plain state dicts
written by ``torch.save``; ``common.pt`` has rsl-rl's own keys at the top level (``actor_state_dict``,
``critic_state_dict``, ``optimizer_state_dict``, ``iter``, ``infos``), so rsl-rl's ``OnPolicyRunner.load()`` opens
it, and ftrain's state under ``ftrain``. ``state_sha256`` is :func:`state_digest` of :func:`learned_state`."""
PACKED_STATE_FORMATS = (2, 3)
"""ftrain 0.1's packed tensors (one flat tensor per dtype): refused with one line, never quarantined."""
CHECKPOINTS = "checkpoints"
POLICIES = "policies"
"""Where policy snapshots go: ``policies/step-N``, beside ``checkpoints/`` (``ftrain.policy.snapshots``)."""
MANIFEST = "MANIFEST.json"
QUARANTINED = "QUARANTINED.json"
COMMON = "common.pt"
"""The state every rank shares (models, optimizer, counters, hooks), written once."""
VERIFIED, INCOMPLETE, CORRUPT, QUARANTINE = "verified", "incomplete", "corrupt", "quarantined"
UNSETTLED = "unsettled"
"""A writer's own step whose commit failed and whose manifest it could not look at: never deleted by its retention."""


def shown(status: str) -> str:
    """A step's status as the commands print it: a scan checks a verified step's manifest and file sizes, not its
    SHA-256s (``ftrain ckpt verify`` reads those), so to a user it is ``committed``."""
    return "committed" if status == VERIFIED else status


def is_timing(metric: str) -> bool:
    """A metric that is wall time (``iteration_time``, ``time/env_ms``...): kept out of manifests and policy lineages,
    which identical runs must write alike."""
    return metric.endswith("_time") or metric.startswith("time/")


def recorded_metrics(metrics: dict[str, float]) -> dict[str, float | None]:
    """The metrics a manifest or a policy lineage records: no timing (:func:`is_timing`), and a metric not measured
    yet (NaN) or infinite as null, since JSON has neither (``jq`` and most readers refuse the ``NaN`` and ``Infinity``
    Python would write)."""
    return {key: value if math.isfinite(value) else None for key, value in metrics.items() if not is_timing(key)}


DIGEST = "manifest_sha256"
"""The manifest's own SHA-256, of its other keys as canonical JSON (:func:`manifest_digest`): a manifest damaged where
it still parses (a byte of a key or a number) is corrupt, not a step with other counters. A manifest without it (an
older ftrain's) verifies by its file list and the types of its fields (``_FIELDS``) alone."""
STEP_DIR = re.compile(r"^step-(\d+)$")
"""A step's directory in a URL a user names (``step-120`` too)."""
CANONICAL_STEP_DIR = re.compile(r"^step-(\d{9}|[1-9]\d{9,})$")
"""A step's directory as ``step_dir`` names it: what a listing counts as a step. Another spelling of its number (a copy
as ``step-0000000120``) is not one, where two directories would claim one step."""
_SHA256 = re.compile(r"^[0-9a-f]{64}$")
_RESERVED = {"format_version", "step", "files", DIGEST}


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


NEVER_COMMITTED = Problem(MANIFEST, "missing: not committed (a save cut short, or in flight)")


@dataclass
class Verification:
    step: int
    problems: list[Problem] = field(default_factory=list)
    manifest: dict | None = None
    """The parsed manifest, if it parsed."""

    @property
    def ok(self) -> bool:
        return not self.problems

    @property
    def never_committed(self) -> bool:
        """No manifest, by a direct look: an abandoned save, which may be deleted."""
        return NEVER_COMMITTED in self.problems


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


def parse_checkpoint_url(url: str, directory: str = CHECKPOINTS) -> tuple[str, int | None]:
    """Split the URL of one step (``<root>/checkpoints/step-000000120``, or ``step-000000120`` in ``checkpoints/``)
    into root and step; else ``(url, None)``. ``directory``: the one that holds the steps (``policies`` for a policy
    snapshot's)."""
    for spelt in spellings(url):
        head, _, last = spelt.rstrip("/").rpartition("/")
        match = STEP_DIR.match(last)
        if match is not None and (head == directory or head.endswith("/" + directory)):
            return head[: -len(directory)].rstrip("/") or ("/" if head.startswith("/") else "."), int(match[1])
    return url, None


def spellings(url: str) -> list[str]:
    """``url``; for a local path, by its name (``..`` resolved), then the real one, absolute, through symbolic links:
    a step named from inside the directory that holds it (``step-000000120`` in ``checkpoints/``) is known by the
    names above it, a link into a step is that step, and so is a path through a run's linked ``checkpoints/``."""
    if "://" in url:
        return [url]
    return list(dict.fromkeys([os.path.normpath(url), os.path.realpath(url)]))


def encode(state: dict) -> bytes:
    """``state`` as a ``torch.save`` file."""
    import torch  # here, not at the top: the manifest-only commands (ls, verify, prune) start in a tenth of the time

    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def decode(data: bytes, name: str = "checkpoint data") -> dict:
    """Load with ``weights_only=True``: tensors, numbers, strings, lists and dicts; anything else is refused."""
    import torch

    try:
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as exc:
        raise CorruptCheckpoint(f"{name} is not loadable as plain data: {_load_failure(exc)}") from None
    if not isinstance(state, dict):
        raise CorruptCheckpoint(f"{name} holds a {type(state).__name__}, not a dict")
    return state


def unloadable_part(state: dict) -> str | None:
    """Where in ``state``, which does not save or load as plain data (``decode``), the first part that does not on its
    own lies, as a path and a type (``ftrain/hooks/mod.Hook#0/obj, a object``): a refused file names the hook or
    metric that holds it. Found by saving and loading the parts, as ``decode`` would; None if every part loads."""
    path, node = [], state
    while isinstance(node, (dict, list, tuple)):
        parts = node.items() if isinstance(node, dict) else enumerate(node)
        found = next(((key, part) for key, part in parts if not _loads(part)), None)
        if found is None:
            break
        path.append(str(found[0]))
        node = found[1]
    return f"{'/'.join(path)}, of type {type(node).__name__}" if path else None


def _loads(part: object) -> bool:
    try:
        decode(encode({"part": part}))
    except Exception:  # it does not pickle (a lambda, a lock), or does not load back
        return False
    return True


def learned_state(common: dict) -> dict:
    """What training has learned, in ``common.pt``: rsl-rl's model and optimizer state dicts (the observation
    normalizers and the learning rate are inside them)."""
    return {key: value for key, value in common.items() if key.endswith("_state_dict")}


def state_digest(state: dict) -> str:
    """SHA-256 of every tensor and plain value in ``state``, in a canonical order: sorted by path (dict keys and list
    positions joined with ``/``), each path followed by its type, and for a tensor its dtype, shape and bytes (C
    order). It depends on the values only, not on dict order or on how a file encodes them."""
    import torch

    digest = hashlib.sha256()
    for path, value in sorted(_leaves(state, ""), key=lambda leaf: leaf[0]):
        if isinstance(value, torch.Tensor):
            tensor = value.detach().cpu().contiguous()
            digest.update(f"{path}\0tensor\0{tensor.dtype}\0{list(tensor.shape)}\0".encode())
            digest.update(tensor.reshape(-1).view(torch.uint8).numpy().tobytes())
        else:
            digest.update(f"{path}\0{type(value).__name__}\0{value!r}\0".encode())
    return digest.hexdigest()


def _leaves(value: object, path: str) -> list[tuple[str, object]]:
    if isinstance(value, dict):
        return [leaf for key, item in value.items() for leaf in _leaves(item, f"{path}/{key}")]
    if isinstance(value, (list, tuple)):
        return [leaf for index, item in enumerate(value) for leaf in _leaves(item, f"{path}/{index}")]
    return [(path, value)]


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
    manifest = {"format_version": FORMAT_VERSION, "step": step, "created": now()} | meta
    manifest["files"] = {name: {"size": e.size, "sha256": e.sha256} for name, e in sorted(files.items())}
    manifest[DIGEST] = manifest_digest(json.loads(_manifest_text(manifest)))  # of what a reader will see
    data = _manifest_text(manifest).encode()
    storage.write_exclusive(f"{step_dir(step)}/{MANIFEST}", data, commit=True)
    return manifest


def newest_generation(storage: Storage) -> int:
    """The generation (``ftrain/identity.py``) that committed the newest step whose manifest reads (0: none), where a
    lease record deleted by hand starts after: on one node no other record of it is kept (``lease.py``)."""
    try:
        steps = sorted(
            (name for name in storage.list_dirs(CHECKPOINTS) if CANONICAL_STEP_DIR.match(name)), reverse=True
        )
    except StorageUnavailable:
        raise
    except (OSError, StorageError) as error:
        raise StorageError(f"checkpoint storage {storage.url} failed while reading its newest step: {error}") from None
    for name in steps[:3]:  # a step cut short has no manifest
        try:
            return int(json.loads(storage.read(f"{CHECKPOINTS}/{name}/{MANIFEST}")).get("generation") or 0)
        except (FileNotFoundError, ValueError, TypeError, RecursionError):
            continue
    return 0


def read_manifest(storage: Storage, step: int, directory: str | None = None) -> dict:
    """The manifest of ``step``: FileNotFoundError if there is none, CorruptCheckpoint if it is not valid.
    ``directory``: where the step lies, if not in its place under ``checkpoints/`` (set aside)."""
    try:
        data = storage.read(f"{directory or step_dir(step)}/{MANIFEST}")
    except IsADirectoryError:
        raise CorruptCheckpoint("a directory, not a file") from None
    try:
        manifest = json.loads(data)
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CorruptCheckpoint(f"not valid JSON ({exc})") from None
    except RecursionError:  # arrays in arrays thousands deep: no manifest ftrain writes
        raise CorruptCheckpoint("not valid JSON (nested too deep)") from None
    if not isinstance(manifest, dict):
        raise CorruptCheckpoint("not a JSON object")
    if DIGEST in manifest and manifest[DIGEST] != manifest_digest(manifest):
        raise CorruptCheckpoint("its content does not match its own digest (damaged after it was written)")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise CorruptCheckpoint(f"format_version {manifest.get('format_version')!r} is not {FORMAT_VERSION}")
    for key, (valid, what) in _FIELDS.items():
        if key in manifest and not valid(manifest[key]):
            raise CorruptCheckpoint(f"{key!r} is {json.dumps(manifest[key])[:40]}, not {what}")
    if manifest.get("step") != step:
        raise CorruptCheckpoint(f"wrong step: says {manifest.get('step')!r}, directory is step {step}")
    files = manifest.get("files")
    if not isinstance(files, dict) or not all(_valid_entry(n, e) for n, e in files.items()):
        raise CorruptCheckpoint("'files' is not a mapping of file name to {size, sha256}")
    return manifest


def _parent(value: object) -> bool:
    return value is None or (
        isinstance(value, dict)
        and is_whole(value.get("step"))
        and isinstance(value.get("state_sha256", ""), str | None)
    )


_FIELDS = {
    "step": (is_whole, "a step number"),
    "iteration": (is_whole, "an iteration number"),
    "world_size": (lambda v: is_whole(v, 1), "a world size of 1 or more"),
    "envs_per_rank": (lambda v: is_whole(v, 1), "a number of environments of 1 or more"),
    "state_format": (is_whole, "a format number"),
    "generation": (is_whole, "a generation number"),
    "attempt": (lambda v: v is None or is_whole(v), "an attempt number"),
    "parent": (_parent, "null or {step, state_sha256 or null}"),
    "origin": (lambda v: v is None or isinstance(v, dict), "null or a mapping"),
    "world_sizes": (
        lambda v: isinstance(v, list) and all(isinstance(p, list) and len(p) == 2 and all(map(is_whole, p)) for p in v),
        "a list of [step, world size]",
    ),
    **{key: (lambda v: isinstance(v, str), "a string") for key in ("state_sha256", "run_id", "config_hash", "created")},
    **{key: (lambda v: isinstance(v, dict), "a mapping") for key in ("config", "metrics", "robot", "arithmetic")},
}
"""The keys readers use, where a manifest has them (an older one may not): the type and range each must have. A
manifest that differs was damaged (one from before ``DIGEST``, or with that key itself damaged) and is corrupt."""


def manifest_digest(manifest: dict) -> str:
    """SHA-256 of ``manifest`` without its ``DIGEST``, as canonical JSON (sorted keys; floats as ``repr``, which
    reads back to the same float), so that it is the same computed from the manifest read back."""
    rest = {key: value for key, value in manifest.items() if key != DIGEST}
    return hashlib.sha256(json.dumps(rest, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def verify_step(storage: Storage, step: int, full: bool = True, directory: str | None = None) -> Verification:
    """Check ``step`` against its manifest: sizes always, SHA-256 digests too when ``full``. ``directory``: where the
    step lies, if not in its place under ``checkpoints/`` (set aside)."""
    return verify_listed(storage, step, storage.list_files(directory or step_dir(step)), full, directory)


def read_verified(storage: Storage, step: int, name: str, manifest: dict) -> dict:
    """Read one file of ``step``, check its size and SHA-256 against ``manifest``, then decode it."""
    return decode(read_verified_bytes(storage, step, name, manifest), storage.where(f"{step_dir(step)}/{name}"))


def read_verified_bytes(storage: Storage, step: int, name: str, manifest: dict) -> bytes:
    """Read one file of ``step`` and check its size and SHA-256 against ``manifest``."""
    entry = manifest["files"].get(name)
    where = storage.where(f"{step_dir(step)}/{name}")
    if entry is None:
        raise CorruptCheckpoint(f"{where} is not listed in the manifest of step {step}")
    try:
        data = storage.read(f"{step_dir(step)}/{name}")
    except FileNotFoundError:
        raise CorruptCheckpoint(f"{where} is missing") from None
    problem = content_problem(name, data, entry)
    if problem:
        raise CorruptCheckpoint(f"{where}: {problem.reason}")
    return data


def verify_listed(
    storage: Storage, step: int, present: dict[str, int], full: bool, directory: str | None = None
) -> Verification:
    """``verify_step`` with the directory's listing ``present`` (name -> size) already at hand. The manifest is read
    even where the listing lacks it: a listing can lag behind the files (a shared filesystem that caches directories,
    NFS across nodes; an fsspec listings cache), and a step taken for never committed may be deleted. A shard the
    listing lacks makes the step corrupt, which is set aside, never deleted."""
    result, directory = Verification(step), directory or step_dir(step)
    if MANIFEST not in present:
        storage.forget_listing(directory)
    try:
        result.manifest = read_manifest(storage, step, directory)
    except FileNotFoundError:
        result.problems.append(NEVER_COMMITTED)
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
                problem = content_problem(name, storage.read(f"{directory}/{name}"), entry)
            except FileNotFoundError:
                problem = Problem(name, "missing")
            if problem:
                result.problems.append(problem)
    return result


def content_problem(name: str, data: bytes, entry: dict) -> Problem | None:
    """What is wrong with ``data`` as the file ``name`` its manifest ``entry`` lists (size, SHA-256); None: nothing."""
    if len(data) != entry["size"]:
        return Problem(name, f"size mismatch: {len(data)} bytes, manifest says {entry['size']}")
    digest = hashlib.sha256(data).hexdigest()
    if digest != entry["sha256"]:
        return Problem(name, f"sha256 mismatch: {digest[:12]}..., manifest says {entry['sha256'][:12]}...")
    return None


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


def human_size(n: int) -> str:
    """``n`` bytes for a person: ``512 B``, ``5.3 KiB``, ``1.2 GiB``."""
    value, unit = float(n), 0
    while value >= 1024 and unit < len(_UNITS) - 1:
        value, unit = value / 1024, unit + 1
    return f"{n} B" if unit == 0 else f"{value:.1f} {_UNITS[unit]}"


_UNITS = ("B", "KiB", "MiB", "GiB", "TiB")


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
