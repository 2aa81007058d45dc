"""Typed run configuration: YAML file + dotted ``key=value`` overrides, validated with one-line errors; and the paths
on this machine that a run or a command writes (the storage where local, the log directory, an output file), made or
tried before any work, so that one that cannot be written is one line, not a traceback halfway through.

Torch-free on purpose: the supervisor loads and validates the config before it launches anything. Imports: values,
errors, redact, log_dir_lock.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import errno
import hashlib
import importlib.util
import json
import math
import os
import tempfile
import typing
import urllib.parse
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from ftrain.errors import UserError, did_you_mean
from ftrain.log_dir_lock import STORAGE_FILE
from ftrain.redact import Url, display_url, display_urls, redact_options, without_hidden
from ftrain.values import (
    STORAGE_OPTION,
    build,
    dotted,
    parse_amount,
    parse_value,
    set_dotted,
    storage_option_overrides,
)

POLICY_FORMATS = ("torchscript", "onnx")
"""The file formats a policy is exported and snapshotted in."""
NO_URL, AUTO = Url(""), Url("auto")  # defaults of the URL keys: immutable, so shared


@dataclass
class EnvConfig:
    id: str = "HalfCheetah-v5"
    """A gymnasium id whose env is a MuJoCo ``MujocoEnv``: gymnasium's own, or your own as ``module:EnvId`` (importing
    ``module`` registers ``EnvId``) or as a plain id registered by a module in ``imports``."""
    imports: list[str] = field(default_factory=list)
    """Modules to import before the env is made (they register your envs; hooks' modules may go here too), from the
    working directory or the installed packages: every process that makes the env imports them."""
    num_envs: int = 16
    """Environments per rank (with ``total_envs``: total_envs / ranks, set at start)."""
    total_envs: int = 0
    """Environments of all ranks together (0: ``num_envs`` per rank). With it, the ranks share a fixed set of
    environments, and a resume at another world size hands every environment on by its global index: the same
    training continues (docs/checkpoints.md, "Resume and resize")."""
    kwargs: dict = field(default_factory=dict)
    """Passed to ``gymnasium.make`` for each environment (e.g. ``max_episode_steps``, which must be set somewhere:
    ``ftrain.policy.robot.check_trainable``)."""

    def in_all(self, world_size: int) -> int:
        """The environments of all ``world_size`` ranks together, however they are counted."""
        return self.total_envs or self.num_envs * world_size


@dataclass
class PolicyConfig:
    hidden_dims: list[int] = field(default_factory=lambda: [64, 64])
    activation: str = "elu"
    obs_normalization: bool = True
    init_noise_std: float = 1.0
    obs_clip: float = 0.0
    """Clip normalised observations to ±``obs_clip`` (0: no clipping; SB3's VecNormalize clips at 10)."""
    obs_normalization_until: int = 0
    """Freeze the observation normalizers once they have seen this many observations, all ranks together (0: never;
    rsl-rl's ``EmpiricalNormalization(until=...)``): inputs that stop shifting under a policy that still learns."""
    std_type: str = "scalar"
    """How the actor's learned action noise is parameterised: ``scalar`` (the std itself) or ``log`` (its log)."""
    final_noise_std: float = 0.0
    """A ceiling on the action noise that falls linearly from ``init_noise_std`` to this at
    ``algorithm.schedule_iterations`` (0: none; ``ftrain.policy.noise_ceiling``)."""


@dataclass
class AlgorithmConfig:
    """Arguments of rsl-rl's PPO (and, for distillation, of its Distillation algorithm), and of ftrain's PPO."""

    class_name: str = "PPO"
    num_learning_epochs: int = 5
    num_mini_batches: int = 4
    clip_param: float = 0.2
    gamma: float = 0.99
    lam: float = 0.95
    value_loss_coef: float = 1.0
    entropy_coef: float = 0.0
    learning_rate: float = 1e-3
    max_grad_norm: float = 1.0
    use_clipped_value_loss: bool = True
    schedule: str = "adaptive"
    schedule_iterations: int = 0
    """``schedule=linear`` (else ``adaptive``, by ``desired_kl``, or ``fixed``): the iteration where the rate is 0."""
    desired_kl: float = 0.01
    normalize_advantage_per_mini_batch: bool = False
    reshuffle_each_epoch: bool = False  # rsl-rl draws one split into minibatches for all epochs
    gradient_length: int = 24
    """Distillation only: steps per truncated back-propagation."""
    loss_type: str = "mse"
    """Distillation only: ``mse`` or ``huber``."""


@dataclass
class RewardConfig:
    normalize: bool = False
    """Divide rewards by the running std of the discounted return (``algorithm.gamma``), as SB3's VecNormalize."""
    clip: float = 10.0
    """With ``normalize``: clip the normalised rewards to [-clip, clip]."""


@dataclass
class CheckpointConfig:
    interval: int | str = 10
    """Save every N iterations, every so long (``"30s"``, ``"5m"``), or ``"auto"`` (by the measured cost of a save and
    ``max_overhead``: see ``ftrain.ckpt.schedule``); the final iteration is always saved."""
    max_overhead: float = 0.02
    """``interval=auto``: the fraction of training time that saving may take."""
    max_unsaved: int | str = "10m"
    """While saves fail, train on for this much work (iterations, or ``"10m"``...) past the newest commit, then pause
    until the storage takes the newest state."""
    keep_last: int = 3
    keep_best: int = 1
    best_metric: str = "mean_return"
    keep_every: int = 0
    """Save and keep every step that is a multiple of this, as a milestone, whatever the interval (0: none)."""
    pinned: list[int] = field(default_factory=list)
    """Steps saved and kept whatever the interval and retention's other rules."""
    async_save: bool = True
    spool: bool = True
    """On a remote storage and one node: every step goes to ``<log_dir>/spool`` on local disk first, and a restart
    resumes from there when it is newer (also while the storage is down): see ``ftrain.ckpt.spool``."""
    retries: int = 4
    """Retries of a transient storage error, with bounded exponential backoff."""


@dataclass
class StorageConfig:
    url: Url = NO_URL
    """Local path or fsspec URL; default ``runs/<name>``."""
    options: dict = field(default_factory=dict)
    """fsspec storage options (for s3: ``endpoint_url``, ``key``, ``secret``...)."""
    plain_writes: bool = False
    """Accept a storage without conditional writes (not local, not an S3 that honours them; see ``ckpt/cas.py``)."""

    def __post_init__(self) -> None:
        self.options = without_hidden(self.options)  # a saved config's hidden credentials are none


class Switched:
    """A config section that is off until any of its keys is set."""

    @property
    def enabled(self) -> bool:
        return self != type(self)()


@dataclass
class WandbConfig(Switched):
    """Weights & Biases, on when any key is set (``pip install 'ftrain[wandb]'``); empty keys: W&B's own defaults."""

    project: str = ""
    """Default when W&B is on: the run's name."""
    entity: str = ""
    group: str = ""
    tags: list[str] = field(default_factory=list)
    mode: str = ""
    """``online``, ``offline`` (sync later with ``wandb sync``) or ``disabled``; empty: ``WANDB_MODE`` or online."""


@dataclass
class MlflowConfig(Switched):
    """MLflow, on when any key is set (``pip install 'ftrain[mlflow]'``)."""

    tracking_uri: Url = NO_URL
    """An MLflow server (``http://host:5000``) or store (``sqlite:///mlflow.db``); empty: ``MLFLOW_TRACKING_URI`` or
    MLflow's default."""
    experiment: str = ""
    """Default when MLflow is on: the run's name."""


@dataclass
class LogConfig:
    console: bool = True
    console_saves: str = "milestones"
    """Which committed saves get a line of their own on the console: ``milestones`` (a process's first, each quarter
    of the run, the last; the progress line says how long ago the newest was) or ``every`` (``-v``)."""
    tensorboard: bool = True
    csv: bool = True
    wandb: WandbConfig = field(default_factory=WandbConfig)
    mlflow: MlflowConfig = field(default_factory=MlflowConfig)

    def trackers(self) -> list[str]:
        """The optional trackers turned on, by their package's name, which is also their key's (``log.wandb``)."""
        return [name for name in ("wandb", "mlflow") if getattr(self, name).enabled]


@dataclass
class EvalConfig:
    every: int = 0
    """Evaluate every N iterations and at the run's last (0: never); the mean return becomes metric ``eval_return``,
    so that the final step's is there to compare with a benchmark's and to rank for keep-best."""
    episodes: int = 5
    seed: int = 10_000
    """Evaluation episodes are seeded ``seed``, ``seed + 1``, ...: the same episodes every time."""


@dataclass
class SnapshotConfig:
    every: int = 0
    """Save a deployable policy to ``<storage>/policies/step-N/`` every N iterations (0: never)."""
    keep_last: int = 5
    formats: list[str] = field(default_factory=lambda: list(POLICY_FORMATS))


@dataclass
class HookConfig:
    target: str = ""
    """Import path ``package.module:Class``."""
    every: int = 1
    kwargs: dict = field(default_factory=dict)


@dataclass
class Config:
    name: str = ""
    """Run name; default: the config file's stem."""
    seed: int = 1
    iterations: int = 300
    """Total iterations of the run: a resumed run stops where an uninterrupted one would."""
    num_steps_per_env: int = 24
    torch_threads: int = 1
    resume: Url = AUTO
    """``auto`` (newest verified checkpoint, else fresh), ``never``, or the URL of one checkpoint step."""
    allow_config_change: bool = False
    """Resume even though the checkpoint's training-relevant config differs (its state wins)."""
    log_dir: str = ""
    """Local directory for logs, metrics, heartbeats; default: the storage path if local, else ``runs/<name>``."""
    dist_timeout: float = 60.0
    """Seconds a collective may wait for a peer before failing."""
    shared_memory_all_reduce: bool = True
    """Ranks on one machine meet through shared memory (``ftrain.comm.shm_allreduce``), not gloo's loopback TCP; across
    machines host first (``ftrain.comm.host_first``): only each machine's first rank crosses the network."""
    split_update: bool = True
    """At an even number of ranks the first half learns the actor and the second the critic, on the whole batch
    (``ftrain.train.split``); false: data-parallel, every rank learns both models on its share."""
    teacher: Url = NO_URL
    """Distillation: URL of the teacher's checkpoint (a step or a run's storage)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    algorithm: AlgorithmConfig = field(default_factory=AlgorithmConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    checkpoint: CheckpointConfig = field(default_factory=CheckpointConfig)
    storage: StorageConfig = field(default_factory=StorageConfig)
    log: LogConfig = field(default_factory=LogConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    snapshots: SnapshotConfig = field(default_factory=SnapshotConfig)
    hooks: list[HookConfig] = field(default_factory=list)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def public_dict(self) -> dict:
        """``to_dict`` without credentials: what may be logged, saved in checkpoints or shipped in a policy."""
        data = display_urls(self.to_dict())
        data["storage"]["options"] = redact_options(self.storage.options)
        return data

    def saved_dict(self) -> dict:
        """``public_dict`` with the local paths a run opens made absolute (its storage, log directory and teacher):
        the run's ``config.yaml``, which continues the run from any working directory. ``resume`` stays as typed: the
        run's manifests name their origin so, and a run that has its own history no longer opens it.
        ``allow_config_change`` is not saved: it lets one start through, and a start from this file (edited since,
        maybe) asks again."""
        data = {**self.public_dict(), "allow_config_change": False}
        for section, key in ((data["storage"], "url"), (data, "log_dir"), (data, "teacher")):
            section[key] = _absolute(section[key])
        return data

    def training_hash(self, robot: dict | None = None) -> str:
        """Digest of everything that decides what is trained (``training_part``), with the identity of the ``robot``
        trained (``ftrain.policy.robot.identity``: its env class and model files) unless that is gymnasium's own, so
        that runs from before robots were hashed still resume."""
        data = training_part(self.to_dict())
        if robot is not None and not robot["builtin"]:
            data["robot"] = robot["digest"]
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]


def training_part(data: dict) -> dict:
    """Of a config as a dict (``to_dict``, ``public_dict`` or a manifest's ``config``), what decides what is trained:
    not run length, storage, logging or retention, nor where the env's code is imported from."""
    data = copy.deepcopy(data)
    run_only = ("name", "iterations", "resume", "allow_config_change", "log_dir", "dist_timeout", "checkpoint")
    for key in (*run_only, "storage", "log", "eval", "snapshots", "hooks"):
        data.pop(key, None)
    data["env"].pop("imports", None)  # where the code is found, not what it is: the robot's identity says that
    if data["env"].get("total_envs"):  # the environments per rank follow the world size
        data["env"].pop("num_envs", None)
    defaults = Config().to_dict()
    for key in KEYS_ADDED_LATER:
        section, _, leaf = key.rpartition(".")
        node, default = (data[section], defaults[section]) if section else (data, defaults)
        if leaf in node and node[leaf] == default[leaf]:
            del node[leaf]
    return data


KEYS_ADDED_LATER = ("policy.std_type", "policy.obs_clip", "algorithm.schedule_iterations")
KEYS_ADDED_LATER += ("algorithm.reshuffle_each_epoch", "reward", "shared_memory_all_reduce", "split_update")
KEYS_ADDED_LATER += ("env.total_envs", "policy.obs_normalization_until", "policy.final_noise_std")
"""Training keys newer than the first checkpoints: hashed only when not at their defaults, so older runs resume."""


ELASTIC_NODES_ENV = "FTRAIN_ELASTIC_NODES"
"""``MIN:MAX``: the node counts of an elastic launch, which ftrun (``ftrain/torchrun/agent.py``) tells its workers, so
that a total some world of the launch cannot share is refused at the start, not at that world in the middle of the
run."""


def for_elastic(config: Config, least: int, most: int, per_node: int) -> None:
    """UserError unless every world an elastic run may train at (``least`` to ``most`` nodes of ``per_node`` ranks)
    shares ``env.total_envs`` evenly: asked before training, by the supervisor and by ftrun's workers."""
    worlds = [count * per_node for count in range(least, most + 1)]
    if least == most or not config.env.total_envs:
        for_world(config, worlds[-1])
        return
    odd = [world for world in worlds if config.env.total_envs % world]
    if odd:
        fits = math.lcm(*worlds)  # named where it is a size a run might take
        named = f" (env.total_envs={fits})" if fits <= 8 * worlds[-1] else ""
        raise UserError(
            f"env.total_envs={config.env.total_envs} cannot be shared evenly by the {odd[0]} ranks of "
            f"{odd[0] // per_node} nodes (--nnodes {least}:{most}, {per_node} per node): set a total that "
            f"every world divides{named}, or env.num_envs=N to count per rank"
        )


def for_launch(config: Config, world_size: int, environ: typing.Mapping[str, str] = os.environ) -> Config:
    """``config`` as this world's ranks run it (``for_world``); refused at once where the launch is elastic (ftrun's
    ``ELASTIC_NODES_ENV``) and one of its worlds could not share the environments."""
    least, _, most = environ.get(ELASTIC_NODES_ENV, "").partition(":")
    if least.isdigit() and most.isdigit():
        for_elastic(config, int(least), int(most), int(environ.get("LOCAL_WORLD_SIZE", world_size)))
    return for_world(config, world_size)


def for_world(config: Config, world_size: int) -> Config:
    """``config`` as ``world_size`` ranks run it: with ``env.total_envs``, that many environments shared evenly."""
    total = config.env.total_envs
    if not total:
        return config
    if total % world_size:
        raise UserError(
            f"env.total_envs={total} cannot be shared evenly by {world_size} ranks: use a multiple of {world_size}, "
            f"a number of ranks that divides {total}, or env.num_envs=N to count per rank"
        )
    resolved = copy.deepcopy(config)
    resolved.env.num_envs = total // world_size
    return resolved


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (plain YAML keeps the last without a word)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # ``<<: *base``: its keys may be given again
                continue
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"the key {key!r} is given twice", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep)


def load_config(path: str | None, overrides: list[str] = (), storage: str | None = None) -> Config:
    """Read a YAML config (or the defaults when ``path`` is None), apply overrides, validate. ``iterations=N`` alone
    (no ``algorithm.schedule_iterations=``) sets a linear schedule's horizon to N."""
    data: dict = {}
    if path is not None:
        file = Path(path)
        if not file.exists() or file.is_dir():
            problem = "is a directory" if file.is_dir() else "does not exist"
            raise UserError(f"config file {path!r} {problem}: pass the path of a YAML file such as configs/smoke.yaml")
        try:
            data = yaml.load(file.read_bytes().decode(), _UniqueKeyLoader) or {}
        except UnicodeDecodeError as exc:
            raise UserError(
                f"config file {path!r} is not UTF-8 text (byte {exc.start}): save it as UTF-8 YAML"
            ) from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
            problem = getattr(exc, "problem", None)
            raise UserError(
                f"config file {path!r} is not valid YAML{where}{f' ({problem})' if problem else ''}: fix the syntax"
            ) from None
        if not isinstance(data, dict):
            raise UserError(f"config file {path!r} must hold a mapping of keys to values")
        if not data and not overrides:  # a file saved empty would train the defaults, whatever it was meant to hold
            raise UserError(
                f"config file {path!r} is empty: give it keys (configs/smoke.yaml shows them), or pass key=value "
                "overrides to train the defaults with them"
            )
        _follow_a_moved_run(file, data)
    keys_given = set()  # the dotted keys set on the command line, a section's mapping (env={num_envs: 8}) by its keys
    for before, item in zip(["", *overrides], overrides, strict=False):
        key, sep, raw = item.partition("=")
        if not sep or not key:
            if "=[" in before and "]" not in before:  # key=[64, 64] unquoted: the shell made two words of it
                raise UserError(f"override {before} {item} has a space: quote it as one word, '{before} {item}'")
            raise UserError(f"override {item!r} is not key=value: write it like env.num_envs=8")
        if not all(key.strip().split(".")):
            raise UserError(f"override {item!r} has an empty part in its key: write it like env.num_envs=8")
        value = parse_value(raw)
        _override(data, key.strip(), value, item)
        keys_given |= set(dotted(value, f"{key.strip()}.")) if isinstance(value, dict) else {key.strip()}
    if storage is not None:
        if not storage.strip():
            raise UserError("--storage is empty: pass a directory or a URL, or leave it out for runs/<name>")
        given = [raw for key, _, raw in (item.partition("=") for item in overrides) if key.strip() == "storage.url"]
        if given and parse_value(given[-1]) and not same_storage(str(parse_value(given[-1])), storage):
            shown = f"--storage {display_url(storage)} and storage.url={display_url(given[-1])}"
            raise UserError(f"{shown} name two storages: pass one of them")
        set_dotted(data, "storage.url", storage)
    config = build(Config, data, prefix="")
    config.storage.url, config.log_dir = Url(expand_home(config.storage.url)), expand_home(config.log_dir)
    config.resume = Url(expand_home(config.resume))
    horizon_keys = keys_given & {"iterations", "algorithm.schedule_iterations"}
    if config.algorithm.schedule == "linear" and horizon_keys == {"iterations"}:
        config.algorithm.schedule_iterations = config.iterations
    _count_envs_as_given(config, keys_given)
    if not config.name:
        config.name = Path(path).stem if path else "run"
    if config.name in (".", "..") or any(mark in config.name for mark in ("/", "\\", "\0")):
        raise UserError(
            f"name={config.name!r} names a directory of runs/ (runs/<name>): give one word without '/' or '..', "
            "e.g. name=my-run, and --storage for a place of your choosing"
        )
    if not config.storage.url:
        config.storage.url = Url(f"runs/{config.name}")
    if not config.log_dir:
        config.log_dir = default_log_dir(config.storage.url, config.name)
    validate(config)
    return config


def _follow_a_moved_run(file: Path, data: dict) -> None:
    """A local run's own ``config.yaml`` (``saved_dict``: absolute paths), its storage its log directory (the default),
    read from that directory after it moved: the place the file names is gone, and the file lies in a run's directory
    (its ``storage.txt``). The run goes on where the file lies, storage and logs, and does not make its old place
    again. The test asks nothing that the run changes, so every process of a run (a supervisor and its workers, a
    restart) decides alike; anything else (a copy, whose original is still there, a storage elsewhere) is taken as
    written."""
    here, saved, storage = file.resolve().parent, data.get("log_dir"), data.get("storage")
    url = storage.get("url") if isinstance(storage, dict) else None
    if file.name != "config.yaml" or not isinstance(saved, str) or not isinstance(url, str) or not local_path(url):
        return
    if same_storage(url, saved) and not os.path.lexists(saved) and (here / STORAGE_FILE).is_file():
        data["log_dir"] = storage["url"] = str(here)


def _count_envs_as_given(config: Config, given: set[str]) -> None:
    """An ``env.num_envs=N`` override counts environments per rank, as its name says, over a file's
    ``env.total_envs`` (the shipped configs count them for the whole run); both overridden at once is refused."""
    if "env.num_envs" not in given or not config.env.total_envs:
        return
    if "env.total_envs" in given:
        raise UserError(
            f"env.num_envs={config.env.num_envs} (per rank) and env.total_envs={config.env.total_envs} (in all) "
            "both count the environments: give one of them"
        )
    config.env.total_envs = 0


def storage_options(words: list[str]) -> dict:
    """The fsspec storage options of ``--storage-option`` words (see ``storage_option_overrides``)."""
    return load_config(None, storage_option_overrides(words)).storage.options


def check_options_used(words: list[str], urls: list[str]) -> None:
    """``--storage-option`` words given where every storage the command opens (``urls``; "" for none) is a local
    path, which fsspec opens without a word about them: a remote URL written without its protocol, most likely."""
    places = [url for url in urls if url]
    if words and places and all(local_path(url) for url in places):
        keys = ", ".join(dict.fromkeys(word.partition("=")[0].strip() for word in words))
        raise UserError(
            f"{STORAGE_OPTION} {keys}: {display_url(places[0])} is a local path, where storage options do nothing: "
            f"write the remote storage's URL with its protocol (s3://..., gs://...), or leave {STORAGE_OPTION} out"
        )


def config_from_dict(data: dict) -> Config:
    """The Config a checkpoint or an exported policy recorded (``Config.public_dict()``), typed and checked."""
    return build(Config, data, prefix="")


LOCAL_PROTOCOLS = ("file://", "local://")
"""fsspec's names of this machine's file system."""


def expand_home(path: str) -> str:
    """A local path written with ``~`` (in a config file, or quoted on the command line) as the shell would expand
    it: fsspec expands it for the checkpoints, so the logs, the locks and the messages must too."""
    return os.path.expanduser(path) if path.startswith("~") and "://" not in path else path


def storage_key(url: str) -> str:
    """One string for a storage however it is spelt: a local one's real path (relative, ``file://``, through links),
    else its URL without credentials or a trailing slash."""
    path = local_path(url)
    return os.path.realpath(path) if path else display_url(url).rstrip("/")


def local_path(url: str) -> str:
    """The path of a storage on this machine's file system, else "": a plain path as it is, a ``file://`` or
    ``local://`` URL as RFC 8089 reads it (``file:///a%20b`` and ``file://localhost/a%20b`` are ``/a b``, where fsspec
    takes both literally). UserError for a URL that names another host (``file://tmp/x``, one slash short: fsspec
    would write a directory ``tmp`` here) and for a NUL byte, which no path holds."""
    protocol = next((protocol for protocol in LOCAL_PROTOCOLS if url.lower().startswith(protocol)), "")
    if protocol:
        host, slash, rest = url[len(protocol) :].partition("/")
        if host.lower() not in ("", "localhost"):
            raise UserError(
                f"storage URL {display_url(url)!r} names the host {host!r}: write {protocol}/{host}/{rest} (three "
                f"slashes) for the absolute path /{host}/{rest}, or a plain path for a relative one"
            )
        path = slash + urllib.parse.unquote(rest)
    else:
        path = url if "://" not in url else ""
    if "\0" in path:
        raise UserError(f"storage {display_url(url)!r} holds a NUL byte, which no path can: fix the path")
    return path


def _absolute(url: str) -> str:
    """A plain local path made absolute (``~`` expanded); a URL (``file://`` ones are absolute already) or "" as it
    is."""
    return os.path.abspath(expand_home(url)) if url and "://" not in url else url


def storage_identity(url: str) -> str:
    """Which storage a run lives in, as trackers may be told it: without credentials, a local path made absolute."""
    return display_url(_absolute(url) or os.getcwd())


def same_storage(one: str, other: str) -> bool:
    """Whether two spellings name one storage: the same local directory (``/x``, ``/x/``, ``file:///x``, ``/a/../x``),
    else the same URL but for a trailing slash."""
    return len({storage_identity(local_path(url) or url).rstrip("/") for url in (one, other)}) == 1


def local_directories(config: Config) -> dict[str, str]:
    """The directories of this machine that a run writes: the storage where it is local, and the log directory."""
    directories = {"storage": local_path(config.storage.url), "log_dir": config.log_dir}
    return {what: path for what, path in directories.items() if path}


CANNOT_BE_MADE = (errno.ENOENT, errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOTDIR)
"""What ``mkdir`` answers for a path that will never be made as it is: the user's to fix, not an outage."""


def make_local_directories(config: Config) -> list[str]:
    """The run's local directories, made once its config and env passed their checks: one that cannot be made (a
    read-only mount, /proc, no permission) is one line here, not a traceback from the first write. A mount that fails
    otherwise (EIO, a stale handle) is an outage, which the storage's own calls wait out. Returns the directories it
    made, deepest first, for ``remove_if_empty``."""
    made = []
    for what, path in local_directories(config).items():
        missing = []
        for directory in (full := Path(os.path.abspath(path)), *full.parents):
            if os.path.lexists(directory):
                break
            missing.append(str(directory))
        try:
            os.makedirs(path, exist_ok=True)
        except OSError as error:
            if error.errno in CANNOT_BE_MADE:
                fix = "pass a directory you can write"
                raise UserError(f"{what} {path} cannot be made ({error.strerror}): {fix}") from None
        made.extend(missing)
    return made


def remove_if_empty(directories: list[str]) -> None:
    """Remove those of ``directories`` (deepest first) that are still empty: a run refused before it wrote anything
    (another run holds its storage) leaves no directory behind. ``rmdir`` removes nothing else."""
    for directory in directories:
        with contextlib.suppress(OSError):
            os.rmdir(directory)


def blocking_file(path: str) -> str | None:
    """The file that keeps ``path`` from being a directory: ``path`` itself, or the nearest part of it that exists,
    where that is not a directory; None if ``path`` is a directory or can be made one."""
    path = os.path.abspath(path)
    while not os.path.lexists(path) and os.path.dirname(path) != path:
        path = os.path.dirname(path)
    return path if os.path.exists(path) and not os.path.isdir(path) else None


def _override(data: dict, key: str, value: object, item: str) -> None:
    """Set ``key`` to ``value`` in the config's ``data``; a section (``env``) takes a mapping, merged into what the
    file set there (``env={num_envs: 8}`` keeps the file's ``env.id``); anything else set on a section is refused:
    ``env=null`` replaced the file's whole section with the defaults."""
    section: object = Config
    for part in key.split("."):
        names = {field.name for field in dataclasses.fields(section)} if dataclasses.is_dataclass(section) else set()
        section = typing.get_type_hints(section)[part] if part in names else None
    if not dataclasses.is_dataclass(section):
        set_dotted(data, key, value)  # a value, or a key ``build`` names as unknown
        return
    if not isinstance(value, dict):
        example = dataclasses.fields(section)[0].name
        raise UserError(f"override {item}: {key} is a section, not a value: set its keys, e.g. {key}.{example}=...")
    for name, inner in value.items():
        _override(data, f"{key}.{name}", inner, item)


def check_writable(path: Path, option: str, fix: str = "") -> None:
    """UserError unless ``path`` can be written, said before the work that makes its contents. It tries: a file made
    and dropped in ``path`` where it is a directory, else in the nearest directory that exists (root passes every
    permission check, /proc, read-only mounts and immutable directories refuse anyway), or ``path`` opened to append
    where it is a file (its contents untouched). ``option``: the flag that chooses the path; ``fix``: what the line
    says to do (default: pass that flag another path)."""
    where = path if path.exists() else next(parent for parent in path.absolute().parents if parent.exists())
    a_file = where == path and not path.is_dir()
    try:
        if a_file:
            path.open("ab").close()
        else:
            tempfile.TemporaryFile(dir=where).close()
    except OSError as error:
        why = error.strerror or str(error)
        takes = " takes no new file" if where.is_dir() else ""
        detail = why if a_file else f"it{takes}: {why}" if where == path else f"{where}{takes}: {why}"
        raise UserError(f"cannot write {path} ({detail}): {fix or f'pass {option} a path you can write to'}") from None


def default_log_dir(storage_url: str, name: str) -> str:
    """Logs go next to the checkpoints when storage is local, else to ``runs/<name>/<the storage>`` on this machine
    (``s3://bkt/exp1`` -> ``runs/exp/s3/bkt/exp1``): two runs of one config on two storages keep their logs apart."""
    if local := local_path(storage_url):
        return local
    shown = display_url(storage_url).partition("?")[0]  # a SAS token's query rotates
    protocol, _, where = shown.partition("://")
    parts = [part for part in where.split("/") if part not in ("", ".", "..")]
    return "/".join(["runs", name, protocol, *parts])


SEEDS = 2**32
"""How many seeds numpy and gymnasium take: 0 to 2**32 - 1."""


def validate(config: Config) -> None:
    """Range checks that types alone cannot express. ``env.id`` is checked by ``ftrain.policy.robot`` (which makes
    the env) and ``ftrain.train.env_ids`` (gymnasium's registry, for the supervisor), which the CLI runs next."""
    minimums = {  # key: (value, smallest allowed)
        "iterations": (config.iterations, 1),
        "env.num_envs": (config.env.num_envs, 1),
        "env.total_envs": (config.env.total_envs, 0),
        "policy.obs_normalization_until": (config.policy.obs_normalization_until, 0),
        "num_steps_per_env": (config.num_steps_per_env, 1),
        "torch_threads": (config.torch_threads, 1),
        "algorithm.num_learning_epochs": (config.algorithm.num_learning_epochs, 1),
        "algorithm.num_mini_batches": (config.algorithm.num_mini_batches, 1),
        "algorithm.gradient_length": (config.algorithm.gradient_length, 1),
        "algorithm.schedule_iterations": (config.algorithm.schedule_iterations, 0),
        "checkpoint.keep_last": (config.checkpoint.keep_last, 1),
        "checkpoint.keep_best": (config.checkpoint.keep_best, 0),
        "checkpoint.keep_every": (config.checkpoint.keep_every, 0),
        "checkpoint.retries": (config.checkpoint.retries, 0),
        "eval.every": (config.eval.every, 0),
        "eval.episodes": (config.eval.episodes, 1),
        "snapshots.every": (config.snapshots.every, 0),
        "snapshots.keep_last": (config.snapshots.keep_last, 1),
    }
    for key, (value, minimum) in minimums.items():
        if value < minimum:
            raise UserError(f"{key}={value} must be {'at least 1' if minimum else '0 or more'}")
    if bad := [step for step in config.checkpoint.pinned if step < 0]:
        pinned = config.checkpoint.pinned
        raise UserError(f"checkpoint.pinned={pinned} holds {bad[0]}, which is no step: pin steps 0 or more")
    for key, first, count in (("seed", config.seed, 1), ("eval.seed", config.eval.seed, config.eval.episodes)):
        if not 0 <= first <= SEEDS - count:  # the seeds of numpy and gymnasium; evaluation uses ``count`` of them
            raise UserError(f"{key}={first} is out of range: use a seed from 0 to {SEEDS - count}")
    if not config.policy.hidden_dims or min(config.policy.hidden_dims) < 1:
        raise UserError(
            f"policy.hidden_dims={config.policy.hidden_dims} must list one or more layer widths of at least 1, "
            "e.g. [256, 256]"
        )
    algorithm, policy = config.algorithm, config.policy
    ranges = {  # key: (value, low, high, whether low itself is allowed, what the range is)
        "algorithm.gamma": (algorithm.gamma, 0.0, 1.0, True, "a discount between 0 and 1"),
        "algorithm.lam": (algorithm.lam, 0.0, 1.0, True, "a GAE lambda between 0 and 1"),
        "algorithm.clip_param": (algorithm.clip_param, 0.0, math.inf, False, "a positive clip range, e.g. 0.2"),
        "algorithm.learning_rate": (algorithm.learning_rate, 0.0, math.inf, False, "a positive rate, e.g. 3e-4"),
        "algorithm.max_grad_norm": (algorithm.max_grad_norm, 0.0, math.inf, False, "a positive norm, e.g. 1.0"),
        "algorithm.value_loss_coef": (algorithm.value_loss_coef, 0.0, math.inf, True, "0 or more, e.g. 0.5"),
        "algorithm.entropy_coef": (algorithm.entropy_coef, 0.0, math.inf, True, "0 or more, e.g. 0.0"),
        "policy.init_noise_std": (policy.init_noise_std, 0.0, math.inf, False, "a positive action noise, e.g. 1.0"),
        "policy.obs_clip": (policy.obs_clip, 0.0, math.inf, True, "0 (no clipping) or a positive bound, e.g. 10"),
    }
    if policy.final_noise_std:  # 0: no ceiling
        what = "0 (no ceiling) or up to policy.init_noise_std"
        ranges["policy.final_noise_std"] = (policy.final_noise_std, 0.0, policy.init_noise_std, False, what)
    if algorithm.schedule == "adaptive":  # the rate's KL bound: unused by the other schedules
        ranges["algorithm.desired_kl"] = (algorithm.desired_kl, 0.0, math.inf, False, "a positive KL bound, e.g. 0.01")
    for key, (value, low, high, closed, what) in ranges.items():
        if not math.isfinite(value) or not (low <= value <= high if closed else low < value <= high):
            raise UserError(f"{key}={value} is out of range: use {what}")
    choices = {  # key: (value, allowed)
        "algorithm.class_name": (config.algorithm.class_name, ("PPO", "Distillation")),
        "algorithm.schedule": (config.algorithm.schedule, ("adaptive", "fixed", "linear")),
        "algorithm.loss_type": (config.algorithm.loss_type, ("mse", "huber")),
        "policy.std_type": (config.policy.std_type, ("scalar", "log")),
        "policy.activation": (config.policy.activation, ACTIVATIONS),
        "log.console_saves": (config.log.console_saves, ("milestones", "every")),
    }
    for key, (value, allowed) in choices.items():
        if value not in allowed:
            raise UserError(
                f"{key}={value!r} is unknown{did_you_mean(str(value), allowed)}: use {', '.join(allowed[:-1])} or "
                f"{allowed[-1]}"
            )
    batch = config.env.in_all(1) * config.num_steps_per_env
    if config.algorithm.num_mini_batches > batch:
        counted = "env.total_envs" if config.env.total_envs else "env.num_envs"
        raise UserError(
            f"algorithm.num_mini_batches={config.algorithm.num_mini_batches} is more than the {batch} samples of a "
            f"rollout ({counted} x num_steps_per_env): use at most {batch}"
        )
    if not config.snapshots.formats or set(config.snapshots.formats) - set(POLICY_FORMATS):
        raise UserError(f"snapshots.formats={config.snapshots.formats} is not a list of torchscript and/or onnx")
    parse_amount("checkpoint.interval", config.checkpoint.interval, auto=True)
    parse_amount("checkpoint.max_unsaved", config.checkpoint.max_unsaved)
    if not 0 < config.checkpoint.max_overhead < 1:
        raise UserError(f"checkpoint.max_overhead={config.checkpoint.max_overhead} must be a fraction between 0 and 1")
    for what, path in local_directories(config).items():
        if (file := blocking_file(path)) is not None:
            named = "" if file == os.path.abspath(path) else f" ({file} is a file)"
            raise UserError(f"{what} {path} is not a directory{named}: pass a directory path (made if missing)")
    if config.dist_timeout <= 0:
        raise UserError(f"dist_timeout={config.dist_timeout} must be a positive number of seconds")
    if config.algorithm.class_name == "Distillation" and not config.teacher:
        raise UserError("algorithm.class_name=Distillation needs a teacher: add teacher=<checkpoint URL>")
    if config.teacher and config.algorithm.class_name != "Distillation":
        raise UserError(
            f"teacher={display_url(config.teacher)} is for distillation: set algorithm.class_name=Distillation (as "
            "configs/distill_halfcheetah.yaml does), or drop teacher="
        )
    if config.algorithm.schedule == "linear" and config.algorithm.schedule_iterations < 1:
        raise UserError("algorithm.schedule=linear needs algorithm.schedule_iterations=N: the rate is 0 at iteration N")
    if config.policy.final_noise_std and config.algorithm.class_name != "PPO":
        raise UserError("policy.final_noise_std is PPO's action noise: unset it for algorithm.class_name=Distillation")
    if config.policy.final_noise_std and config.algorithm.schedule_iterations < 1:
        raise UserError(
            "policy.final_noise_std needs algorithm.schedule_iterations=N, the iteration where the noise's ceiling "
            "reaches it: use algorithm.schedule=linear with it"
        )
    if config.reward.clip <= 0:
        raise UserError(f"reward.clip={config.reward.clip} must be a positive number")
    if config.log.wandb.mode not in WANDB_MODES:
        raise UserError(f"log.wandb.mode={config.log.wandb.mode!r} is unknown: use online, offline or disabled")
    for module in config.log.trackers():  # installed; whether it imports is the user code's check (train.user_code)
        if importlib.util.find_spec(module) is None:
            fix = f"pip install 'ftrain[{module}]', or unset log.{module}"
            raise UserError(f"log.{module} is set but {module} is not installed: {fix}")
    before, sqlite, database = config.log.mlflow.tracking_uri.reveal().partition("sqlite:///")
    if config.log.mlflow.enabled and sqlite and not before:  # MLflow retries a file it cannot open for 100 s
        fix = "pass log.mlflow.tracking_uri a sqlite:/// file you can write to"
        check_writable(Path(database), "log.mlflow.tracking_uri", fix)
    project = config.log.wandb.project or config.name  # the run's name where no project is set
    forbidden = " ".join(sorted(set(project) & set(WANDB_PROJECT_FORBIDS)))
    if config.log.wandb.enabled and (forbidden or len(project) > 128):
        key = "log.wandb.project" if config.log.wandb.project else "name"
        raise UserError(
            f"{key}={project!r} is no W&B project name ({forbidden or f'{len(project)} characters'}): set "
            f"log.wandb.project to at most 128 characters without {' '.join(WANDB_PROJECT_FORBIDS)}"
        )
    for number, hook in enumerate(config.hooks):
        if ":" not in hook.target:
            raise UserError(f"hook target {hook.target!r} must be an import path like package.module:Class")
        if hook.every < 1:
            raise UserError(f"hooks[{number}].every={hook.every} must be at least 1 (its hook runs every N iterations)")


WANDB_MODES = ("", "online", "offline", "disabled")
WANDB_PROJECT_FORBIDS = "/\\#?%:"
"""The characters W&B refuses in a project's name, which it also keeps to 128 characters (``wandb_settings``,
``validate_project``): found by ``wandb.init``, after training has started, it would leave the run untracked."""

ACTIVATIONS = ("elu", "selu", "relu", "crelu", "lrelu", "tanh", "sigmoid", "softplus", "gelu", "swish", "mish")
ACTIVATIONS += ("identity",)  # rsl-rl's names (resolve_nn_activation)
