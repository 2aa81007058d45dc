"""Resume: which step a run starts from, whether it fits, and loading it on every rank.

At another world size the run resizes, by one rule that depends on (checkpoint, new world size) only: the learned
state (models, optimizer, normalizers, learning rate, counters, hook states) loads exactly on every rank. With
``env.total_envs`` every environment goes on, on the rank that holds its global index, and the same training
continues. Without it, rank r takes the environments and random streams of the checkpoint's rank r where there is
one; ranks beyond the old world start fresh ones, seeded from (run seed, rank, step); shards of ranks beyond the new
world are dropped, and the global batch follows the world size. At the same world size and arithmetic
(``arithmetic.py``) a resume continues bit for bit; on another arithmetic it says so in one line.

Rank 0 decides (newest step that verifies, or the one ``resume=`` names where this storage's history does not
already go on from it; a newer one in this node's spool, see ``spool.py``, also while the storage does not answer) and
tells the others. Every rank then
reads and checks its own files, and the ranks agree on what went wrong, if anything, so that all stop with the
same one line:

- a file that does not match its manifest or is not plain data: an integrity failure; the step is quarantined
  and the next start falls back to an older one (exit 1, which the supervisor retries);
- the storage failing: nothing is marked, the next start tries again (exit 1); the storage not answering at all:
  ``StorageUnavailable`` (exit 7), which the supervisor waits out before it starts again;
- a step that verifies but does not load into this code (a changed model, an rsl-rl upgrade, a hook whose
  ``load_state_dict`` raises): bad input, exit 2, which the supervisor does not retry; the step is left alone.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from ftrain.ckpt.arithmetic import change as arithmetic_change
from ftrain.ckpt.changes import changed_keys, config_change, model_change, robot_change
from ftrain.ckpt.format import (
    COMMON,
    INCOMPLETE,
    PACKED_STATE_FORMATS,
    STATE_FORMAT,
    VERIFIED,
    CorruptCheckpoint,
    parse_checkpoint_url,
    read_verified,
    shard_name,
    step_dir,
)
from ftrain.ckpt.lease import LeaseHeld
from ftrain.ckpt.retention import delete_step
from ftrain.ckpt.spool import FIELD as SPOOL_FIELD
from ftrain.ckpt.spool import Spool
from ftrain.ckpt.steps import clear_newer, quarantine, resolve_checkpoint_url, scan, select_resume
from ftrain.ckpt.storage import Storage, StorageError, StorageUnavailable
from ftrain.comm import group
from ftrain.config import Config
from ftrain.errors import UserError, command, counted, load_error_line
from ftrain.redact import display_url

ORIGIN = "origin"
"""The manifest key (and decision key) of ``Resumed.origin``."""


class Checkpointable(Protocol):
    """What a checkpoint saves and restores: the trainer, as this package sees it."""

    iteration: int
    metrics: dict[str, float]

    def common_state(self) -> dict:
        """The state all ranks share, saved once by rank 0 (``common.pt``)."""

    def rank_state(self) -> dict:
        """This rank's own state (its shard)."""

    def load_state(self, common: dict, rank: dict | None, saved: dict) -> None:
        """Restore what ``common_state`` and ``rank_state`` returned; ``rank`` is None on a rank that the
        checkpoint's world did not have (it starts fresh environments and random streams, from the run's seed, the
        step and its rank). ``saved``: the config the checkpoint was trained with (its manifest's), for what a config
        change let through at this resume (``allow_config_change``) must replace of the state."""

    def rank_state_from(self, shards: list[dict], offset: int) -> dict:
        """This rank's own state from consecutive ranks' ``shards`` of another world size, its environments theirs
        from row ``offset`` on (``env.total_envs``)."""


class CheckpointError(RuntimeError):
    """Saving or loading a checkpoint failed in a way training must not run on from (one-line message)."""


@dataclass(frozen=True)
class Resumed:
    step: int | None
    """The step the run starts from; None for a fresh start."""
    own: bool
    """Whether that step lies in this run's own storage."""
    world_sizes: list
    """``[[first step, world size], ...]``: the run's world sizes so far, this one last."""
    committed: int | None = None
    """The storage's newest committed step as far as the resume knows: ``step``, unless it came from the spool."""
    config_change: str | None = None
    """What changed since ``step`` and was let through (``allow_config_change``, or a lengthened run's learning-rate
    horizon: ``check_compatible``), in words (``ftrain.ckpt.changes``)."""
    digest: str | None = None
    """The ``state_sha256`` of ``step``: the parent of this run's first commit (``lineage.py``)."""
    origin: dict | None = None
    """Where this storage's history started from, if from a step named by ``resume=URL`` (``{"url", "step",
    "state_sha256"}``): every manifest records it (``ORIGIN``), and the same ``resume=URL`` again goes on from this
    storage's newest step."""


def restore(
    trainer: Checkpointable,
    config: Config,
    info: group.RankInfo,
    storage: Storage,
    log: Callable[[str], None],
    robot: dict | None = None,
    spool: Spool | None = None,
    down: StorageUnavailable | None = None,
    arithmetic: list[str] | None = None,
) -> Resumed:
    """Load the step rank 0 chose into ``trainer``, which trains ``robot`` (see ``check_compatible``), from the
    storage, the ``spool`` or another run's storage (``resume=URL``); ``down``: why the storage did not answer when it
    was opened just now (it is not asked again); ``arithmetic``: every rank's (``arithmetic.describe``), to say
    whether the run continues bit for bit."""
    decision = decide(config, storage, log, info.world_size, robot, spool, down) if info.is_main else None
    decision = group.broadcast_object(decision, info)
    if decision["kind"] == "usage":
        raise UserError(decision["why"])
    if decision["kind"] == "storage":
        raise CheckpointError(decision["why"])
    if decision["kind"] == "unavailable":
        raise StorageUnavailable(decision["why"])
    if decision["kind"] == "held":
        raise LeaseHeld(decision["why"])
    if decision["kind"] == "fresh":
        log(decision["why"])
        return Resumed(None, False, [[0, info.world_size]])
    url, step, manifest, spooled = decision["url"], decision["step"], decision["manifest"], decision["spooled"]
    source = spool.storage if spooled else storage if url is None else Storage.open(url, config.storage.options)
    resharded = bool(config.env.total_envs) and manifest["world_size"] != info.world_size
    failure = _load(trainer, source, step, manifest, info.rank, config.env.num_envs if resharded else None)
    failures = [f for f in group.all_gather_object(failure, info) if f]
    where = source.where(step_dir(step))
    for kind in ("unavailable", "integrity", "storage", "fit"):
        reasons = "; ".join(why for failed, why in failures if failed == kind)
        if not reasons:
            continue
        if kind == "fit":
            raise UserError(
                f"checkpoint {where} verifies but does not load into this code ({reasons}): restore the code or "
                "config it was trained with, or start from another step (resume=URL) or --storage; the step is "
                "left as it is"
            )
        if kind == "storage":
            raise CheckpointError(f"checkpoint {where} could not be read ({reasons}): nothing marked, try again")
        if kind == "unavailable":
            raise StorageUnavailable(f"checkpoint {where} could not be read ({reasons}): the storage does not answer")
        if spooled and info.is_main:
            delete_step(spool.storage, step)
        elif url is None and info.is_main:
            quarantine(storage, step, reasons)
        raise CheckpointError(
            f"checkpoint {where} does not match its manifest ({reasons}): "
            f"{'deleted from the spool' if spooled else 'quarantined'}, the next start falls back to an older step"
        )
    log(f"resumed from step {step} ({decision['where']}), iteration {trainer.iteration}")
    saved = manifest["config"]
    current = {**config.public_dict(), "teacher": saved.get("teacher")}  # the student keeps its teacher (load_state)
    change = config_change(saved, current, manifest.get("robot"), robot)
    if change:  # allow_config_change, a horizon that follows the run's length or the same environments counted anew
        why = "allow_config_change=true" if config.allow_config_change else "the learning rate follows iterations"
        if not config.allow_config_change and set(changed_keys(saved, current)) <= ENV_COUNTS:
            why = "the same environments, counted per rank or in all"
        if config.allow_config_change or config.iterations > step:  # a shortened run's horizon trains nothing
            log(f"changed since step {step} ({why}): {change}")
    if moved := arithmetic_change(manifest.get("arithmetic"), arithmetic or []):
        log(f"step {step} was trained on other arithmetic ({moved}): the run continues, not bit for bit")
    world_sizes = manifest.get("world_sizes") or [[0, manifest["world_size"]]]
    if manifest["world_size"] != info.world_size:
        log(resize_line(manifest["world_size"], info.world_size, step, config))
        world_sizes = [*world_sizes, [step, info.world_size]]
    digest = manifest.get("state_sha256")
    return Resumed(step, url is None, world_sizes, decision["committed"], change, digest, decision[ORIGIN])


def resize_line(old: int, new: int, step: int, config: Config) -> str:
    """What a resize does, in one line for the log."""
    total = config.env.total_envs
    if total:
        return (
            f"resized from {old} to {new} ranks at step {step}: env.total_envs={total}, every environment goes on, "
            f"{config.env.num_envs} per rank by global index; the global batch stays {total * config.num_steps_per_env}"
            " per iteration"
        )
    staying = min(old, new)
    kept = _ranks(0, staying) + (" keeps its" if staying == 1 else " keep their")
    parts = [f"resized from {old} to {new} ranks at step {step}: {kept} environments"]
    if new > old:
        start = "starts" if new - old == 1 else "start"
        parts.append(f"{_ranks(old, new)} {start} with fresh ones (seeded from seed {config.seed}, rank, step {step})")
    else:
        parts.append(f"the shards of {_ranks(new, old)} are dropped")
    batch = new * config.env.num_envs * config.num_steps_per_env
    per_rank = f"{config.env.num_envs} envs x {config.num_steps_per_env} steps"
    parts.append(f"the global batch follows: {new} x {per_rank} = {batch} per iteration")
    return "; ".join(parts)


def _ranks(first: int, end: int) -> str:
    return f"rank {first}" if end - first == 1 else f"ranks {first}-{end - 1}"


def _load(
    trainer: Checkpointable, storage: Storage, step: int, manifest: dict, rank: int, envs: int | None = None
) -> list | None:
    """This rank's part of a resume: ``None``, or ``[kind of failure, why]``. ``envs``: this rank's environments,
    where they are taken by global index from the checkpoint's shards (``env.total_envs``, another world size)."""
    try:
        common = read_verified(storage, step, COMMON, manifest)
        if envs is not None:
            first, saved = rank * envs, manifest["envs_per_rank"]
            holders = range(first // saved, (first + envs - 1) // saved + 1)
            shards = [read_verified(storage, step, shard_name(holder), manifest) for holder in holders]
            shard = trainer.rank_state_from(shards, first - holders[0] * saved)
        elif rank < manifest["world_size"]:
            shard = read_verified(storage, step, shard_name(rank), manifest)
        else:
            shard = None
    except CorruptCheckpoint as exc:
        return ["integrity", f"rank {rank}: {exc}"]
    except StorageUnavailable as exc:
        return ["unavailable", f"rank {rank}: {exc}"]
    except (StorageError, OSError) as exc:
        return ["storage", f"rank {rank}: {exc}"]
    try:
        trainer.load_state(common, shard, manifest["config"])
    except Exception as exc:
        return ["fit", f"rank {rank}: {load_error_line(exc)}"]
    return None


def decide(
    config: Config,
    storage: Storage,
    log: Callable[[str], None],
    world_size: int,
    robot: dict | None = None,
    spool: Spool | None = None,
    down: StorageUnavailable | None = None,
) -> dict:
    """On rank 0: ``{"kind": "fresh" | "resume" | "usage" | "storage" | "unavailable" | "held", ...}`` (JSON, for the
    other ranks). A start that does not resume from the spool empties it: it only ever holds the history of this
    start."""
    try:
        decision = _decide(config, storage, log, world_size, robot, spool, down)
    except UserError as error:
        decision = {"kind": "usage", "why": str(error)}
    except LeaseHeld as error:  # the holder's check refused a clean-up: another run holds the storage now
        decision = {"kind": "held", "why": str(error)}
    except StorageUnavailable as error:
        decision = {"kind": "unavailable", "why": f"checkpoint storage {storage.url} does not answer: {error}"}
    except (StorageError, OSError) as error:
        decision = {"kind": "storage", "why": f"checkpoint storage {storage.url} failed while choosing a step: {error}"}
    if spool is not None and decision["kind"] in ("fresh", "resume") and not decision.get("spooled"):
        try:
            if deleted := spool.clear():
                steps = ", ".join(map(str, deleted))
                start = (
                    "is fresh"
                    if decision["kind"] == "fresh"
                    else f"goes on from step {decision['step']} ({decision['where']})"
                )
                log(f"emptied the spool {spool.storage.url} (steps {steps}): this start {start}")
        except (StorageError, OSError) as error:
            log(f"could not empty the spool {spool.storage.url} ({error})")
    return decision


def _decide(
    config: Config,
    storage: Storage,
    log: Callable[[str], None],
    world_size: int,
    robot: dict | None,
    spool: Spool | None,
    down: StorageUnavailable | None,
) -> dict:
    resume = config.resume
    if down is not None and (resume != "auto" or spool is None):
        raise down
    if resume == "never":
        if any(step.status == VERIFIED for step in scan(storage)):
            raise UserError(
                f"resume=never but {storage.url} already holds checkpoints: use resume=auto to continue, or a "
                "new --storage"
            )
        clear_newer(storage, 0, log)
        return {"kind": "fresh", "why": "resume=never: starting fresh"}
    found = select_resume(storage, log=log) if resume != "auto" else None
    from_url = resume != "auto" and not _spool_goes_on(config, storage, spool, found)
    if from_url and (started := _from_url(config, storage, found, log, world_size, robot)) is not None:
        return started
    try:
        if down is None and found is None:
            found = select_resume(storage, log=log)
    except StorageUnavailable as error:
        if spool is None:
            raise
        down = error
    reachable = down is None
    if reachable and found is None:
        _refuse_corrupt(storage)  # before the spool: a storage with steps that do not verify is the user's to look at
    spooled = _spooled(spool, found, reachable, log) if spool is not None else None
    if spool is None and reachable and resume == "auto" and (switched_off := Spool.switched_off(config, storage)):
        switched_off.refuse_to_pass_over(found)
    if spooled is not None:
        step, manifest = spooled
        check_compatible(config, step, manifest, world_size, robot, in_place=False)
        if reachable:
            clear_newer(storage, step, log)
        if not reachable:
            committed, newest = manifest[SPOOL_FIELD]["base"], f"{storage.url} does not answer"
        elif found is None:  # emptied since (this run's own spool), or never committed to
            base = manifest[SPOOL_FIELD]["base"]
            committed, newest = None, "the storage holds no step"
            newest += f" (emptied: this run spooled the step on its step {base})" if base is not None else ""
        else:
            committed, newest = found[0], f"the storage's newest is step {found[0]}"
        where = f"the spool {spool.storage.url}: {newest}"
        return _resume(step, manifest, url=None, where=where, committed=committed, spooled=True)
    if down is not None:
        raise down
    if resume != "auto" and not from_url and found is None:  # the spool it was to go on from did not read
        return _from_url(config, storage, found, log, world_size, robot)
    if found is None:
        clear_newer(storage, 0, log)
        return {"kind": "fresh", "why": f"no verified checkpoint in {storage.url}: starting fresh"}
    step, manifest = found
    check_compatible(config, step, manifest, world_size, robot)
    clear_newer(storage, step, log)
    return _resume(step, manifest, url=None, where="this storage", committed=step)


def _spool_goes_on(config: Config, storage: Storage, spool: Spool | None, found: tuple[int, dict] | None) -> bool:
    """``resume=URL`` on a storage that holds no step, where the spool holds steps of its history: whether they
    go on from that same ``resume=`` (a restart whose commits never reached the storage), then resumed as
    ``resume=auto`` would. Steps of another history are the only copy of it, which this start would delete:
    UserError."""
    if spool is None or found is not None or not (held := spool.held()):
        return False
    shown = display_url(config.resume)
    if (held[0].manifest.get(ORIGIN) or {}).get("url") == shown:
        return True
    spooled = spool.storage.where(step_dir(held[0].step))
    raise UserError(
        f"resume={shown}: {storage.url} holds no step, but the spool holds step {held[0].step} of another history "
        f"of it ({spooled}), its only copy, which this start would delete: copy that directory to "
        f"{storage.where(step_dir(held[0].step))} to go on from it with resume=auto, or delete the spool "
        f"{spool.storage.url} to start from resume={shown}"
    )


def _refuse_corrupt(storage: Storage) -> None:
    """UserError if ``storage`` has no verified step but steps that do not verify."""
    bad = sorted(step.step for step in scan(storage) if step.status != INCOMPLETE)
    if bad:
        raise UserError(
            f"no checkpoint in {storage.url} verifies, and steps {bad} are corrupt: inspect them "
            f"({command('ftrain', 'ckpt', 'ls', storage.url)}), then remove them "
            f"({command('ftrain', 'ckpt', 'prune', storage.url, '--drop-bad')}) to start over, or use another "
            "--storage"
        )


def _from_url(
    config: Config,
    storage: Storage,
    found: tuple[int, dict] | None,
    log: Callable[[str], None],
    world_size: int,
    robot: dict | None,
) -> dict | None:
    """``resume=URL``: the start of this storage's history from that step (of another run's storage, or of this
    one). Its manifests name that step as their ``origin``; where this storage's history already goes on from it (the
    same command again: a restart, a rerun after an interruption), None: the run resumes as with ``resume=auto``, the
    spool included. Another history already here is refused. ``found``: this storage's newest step (``select_resume``).
    """
    shown = display_url(config.resume)
    origin = (found[1].get(ORIGIN) or {}) if found is not None else {}
    if found is None or origin.get("url") != shown:
        try:
            _, step, manifest = resolve_checkpoint_url(config.resume, config.storage.options, log)
        except UserError as error:
            raise UserError(f"resume={shown}: {error}") from None
        digest = manifest.get("state_sha256")
        if found is None:
            check_compatible(config, step, manifest, world_size, robot, in_place=False)
            clear_newer(storage, step, log)
            url = parse_checkpoint_url(config.resume)[0]
            started = {ORIGIN: {"url": shown, "step": step, "state_sha256": digest}}
            return _resume(step, manifest, url=url, where=display_url(url), committed=None) | started
        if digest not in (origin.get("state_sha256"), found[1].get("state_sha256")):
            held = any(
                info.step == step and (info.manifest or {}).get("state_sha256") == digest for info in scan(storage)
            )
            already = (
                f"already holds step {step} and goes on past it (newest: step {found[0]})"
                if held
                else f"already holds checkpoints (newest: step {found[0]}) that do not continue {shown}"
            )
            fix = "resume=auto goes on from them; to start from that step, use another --storage"
            raise UserError(f"{storage.url} {already}: {fix}")
    log(f"resume={shown}: the history of {storage.url} goes on from that step; resuming from its newest")
    return None


def _spooled(spool: Spool, found: tuple | None, reachable: bool, log: Callable[[str], None]) -> tuple | None:
    """The spooled step to resume from (``Spool.newest``); a spool that cannot be read is passed over, with a line:
    it is optional, the storage is not."""
    try:
        return spool.newest(found, reachable, log)
    except (StorageError, OSError, KeyError, TypeError, ValueError) as error:
        log(f"the spool {spool.storage.url} could not be read ({type(error).__name__}: {error}): not resumed from")
        return None


def _resume(
    step: int, manifest: dict, url: str | None, where: str, committed: int | None, spooled: bool = False
) -> dict:
    return {
        "kind": "resume",
        "url": url,
        "step": step,
        "manifest": manifest,
        "where": where,
        "committed": committed,
        "spooled": spooled,
        ORIGIN: manifest.get(ORIGIN),
    }


def check_compatible(
    config: Config, step: int, manifest: dict, world_size: int, robot: dict | None = None, in_place: bool = True
) -> None:
    """UserError unless ``step`` (by its manifest) can continue as this run at ``world_size`` ranks, training ``robot``
    (``ftrain.policy.robot.identity``; None: not checked). ``in_place``: the step lies in this storage as it is (not
    in the spool nor another storage, from which even a start that trains nothing writes it, with this config)."""
    written, versions = manifest.get("state_format", 1), manifest.get("versions", "its versions are not recorded")
    if written in PACKED_STATE_FORMATS:
        raise UserError(
            f"checkpoint step {step} is in ftrain 0.1's packed format (state format {written}); this ftrain reads "
            f"state format {STATE_FORMAT}: resume it with the ftrain that wrote it ({versions}), or start "
            "another --storage"
        )
    if written != STATE_FORMAT:
        raise UserError(
            f"checkpoint step {step} holds training state in format {written}, this ftrain reads format "
            f"{STATE_FORMAT}: resume it with the ftrain that wrote it ({versions}), or start another "
            "--storage"
        )
    saved = manifest["config"]  # another robot or model first: no count of environments mends that
    if changed := model_change(saved, config.public_dict()):
        raise UserError(
            f"checkpoint step {step} holds another model than the config asks for ({changed}): they cannot be loaded "
            "into each other (not even with allow_config_change=true): set the checkpoint's values, or use another "
            "--storage"
        )
    _check_env_counts(config, step, manifest, world_size)
    changed = robot_change(manifest.get("robot"), robot)
    if changed and not config.allow_config_change:
        raise UserError(
            f"checkpoint step {step} was trained with another robot: {changed}: restore it, or pass "
            "allow_config_change=true to go on with the robot as it is now"
        )
    taken = _taken_as_it_is(manifest["config"], config, step if in_place else None)
    if manifest["config_hash"] != config.training_hash(robot) and not config.allow_config_change and not taken:
        keys = config_change(manifest["config"], config.public_dict(), None, None)
        horizon_alone = set(changed_keys(manifest["config"], config.public_dict())) == {HORIZON}
        if horizon_alone and config.algorithm.schedule_iterations == config.iterations:
            keys += f", which iterations={config.iterations} sets"
        elif _horizon_taken(manifest["config"], config, step if in_place else None):  # named apart, as taken
            saved_horizon = manifest["config"]["algorithm"]["schedule_iterations"]
            others = config.public_dict()
            others["algorithm"]["schedule_iterations"] = saved_horizon
            keys = f"{config_change(manifest['config'], others, None, None)}; and {HORIZON} {saved_horizon} -> "
            keys += f"{config.algorithm.schedule_iterations}, which follows iterations={config.iterations} and is taken"
        raise UserError(
            f"checkpoint step {step} was trained with a different config "
            f"({keys or 'hash ' + manifest['config_hash'] + ', now ' + config.training_hash(robot)}): restore the "
            "config, pass allow_config_change=true, or start a new run in another --storage"
        )


HORIZON = "algorithm.schedule_iterations"
"""A linear learning rate's horizon: a change of it that follows the run's length is taken (``_horizon_taken``)."""
ENV_COUNTS = {"env.num_envs", "env.total_envs"}
"""The two ways to count a run's environments (per rank, in all): ``_check_env_counts`` compares the counts."""


def _check_env_counts(config: Config, step: int, manifest: dict, world_size: int) -> None:
    """UserError unless the config at ``world_size`` ranks goes on with the environments of ``step``. Counted per rank
    then and now: the same number per rank (the global batch follows the world size). Counted in all then or now: the
    same number in all, counted in all now where the world size changes (only that hands every environment on by its
    global index)."""
    per_rank, saved_world = manifest["envs_per_rank"], manifest["world_size"]
    saved_total, in_all = per_rank * saved_world, bool(config.env.total_envs)
    if not in_all and not manifest["config"]["env"].get("total_envs"):
        if per_rank != config.env.num_envs:
            raise UserError(
                f"checkpoint step {step} has env.num_envs={per_rank} per rank, the config has {config.env.num_envs}: "
                f"set env.num_envs={per_rank}"
            )
        return
    total = config.env.in_all(world_size)
    if total == saved_total and (in_all or world_size == saved_world):
        return
    saved_ranks = counted(saved_world, "rank")
    has = f"checkpoint step {step} has {saved_total} environments in all ({saved_ranks} x {per_rank})"
    if in_all:
        raise UserError(f"{has}, the config has env.total_envs={total}: set env.total_envs={saved_total}")
    ranks = counted(world_size, "rank")
    resize = ", and a resize hands them on only counted in all" if total == saved_total else ""
    raise UserError(
        f"{has}, the config counts env.num_envs={config.env.num_envs} per rank at {ranks}{resize}: set "
        f"env.total_envs={saved_total} instead of env.num_envs"
    )


def _taken_as_it_is(saved: dict, config: Config, step: int | None) -> bool:
    """Whether every change since ``saved`` (a manifest's config, at ``step``, None where a start writes it anew) is one
    a resume takes without ``allow_config_change``: the teacher's URL (another spelling, or another teacher: a student
    keeps the teacher it started with, whose weights its checkpoint holds, and says so: ``Trainer.load_state``), and a
    linear schedule's horizon that follows the run's length on both sides (``iterations=N`` alone sets it to N:
    ``load_config``): a run started short and lengthened, whose rate then falls to zero at the new end, or asked for no
    more than it has trained, which trains nothing (the trainer says so). A count of the environments per rank where
    it was in all, or the other way round: ``_check_env_counts`` has let only the same environments through."""
    changed = set(changed_keys(saved, config.public_dict())) - {"teacher", *ENV_COUNTS}
    if changed != {HORIZON}:
        return not changed
    return _horizon_taken(saved, config, step)


def _horizon_taken(saved: dict, config: Config, step: int | None) -> bool:
    """Whether the change of a linear schedule's horizon since ``saved`` is one a resume takes (``_taken_as_it_is``)."""
    if saved["algorithm"].get("schedule") != "linear" or config.algorithm.schedule != "linear":
        return False
    horizons = (saved["algorithm"].get("schedule_iterations"), config.algorithm.schedule_iterations)
    follows = horizons == (saved.get("iterations"), config.iterations) and horizons[0] != horizons[1]
    return follows and (horizons[1] > horizons[0] or (step is not None and config.iterations <= step))
