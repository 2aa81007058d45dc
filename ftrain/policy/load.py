"""Trained policies outside training: load one from any ftrain URL, export it, play it.

``load_policy`` accepts
- a run's storage (its newest verified checkpoint) or one checkpoint step ``<root>/checkpoints/step-000000120``;
- a policy snapshot ``<root>/policies/step-000000120`` (written during training, see ``snapshots.py``);
- a file written by ``export`` (TorchScript or ONNX): it carries the config it was trained with as metadata.
Checkpoints and snapshots are verified against their manifest first, and their tensors load with weights_only.

An exported policy is self-contained: the observation normalizer is inside, and it needs only torch (TorchScript) or
onnxruntime (ONNX), not ftrain. It maps a batch of observations ``obs [N, obs_dim]`` to deterministic (mean) actions
``actions [N, num_actions]``.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
from tensordict import TensorDict

from ftrain.ckpt.format import (
    COMMON,
    PACKED_STATE_FORMATS,
    CorruptCheckpoint,
    parse_checkpoint_url,
    read_verified,
    read_verified_bytes,
    step_dir,
)
from ftrain.ckpt.steps import resolve_checkpoint_url
from ftrain.ckpt.storage import Storage
from ftrain.config import Config, config_from_dict
from ftrain.errors import UserError, load_error_line
from ftrain.policy import snapshots
from ftrain.policy.model import OBS_GROUP, actor_actions, build_actor
from ftrain.policy.noise_ceiling import build_noise_ceiling
from ftrain.policy.robot import make_env

METADATA = "ftrain.json"
"""Key of the metadata in an exported file: a TorchScript extra file, an ONNX metadata property."""


@dataclass
class Policy:
    actor: Callable
    """The rsl-rl ``MLPModel`` (eval mode), or for an exported file the loaded TorchScript/ONNX model."""
    config: Config
    """The config the policy was trained with."""
    source: str
    """Where it was loaded from (printable URL)."""
    step: int | None
    manifest: dict | None
    """The verified manifest of its checkpoint or snapshot (None for an exported file)."""
    digest: str
    """The checkpoint's (or snapshot's) ``state_sha256``; for an exported file, the file's SHA-256."""
    exported: str | None = None
    """The format of the exported file it was loaded from; None when ``actor`` is the rsl-rl model."""
    obs_dim: int | None = None
    """The observations an exported file takes (its metadata); None for the rsl-rl model, which checks them itself."""

    def act(self, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        """Actions for observations ``[N, obs_dim]``; an exported policy has only its deterministic ones."""
        if self.exported is None:
            return actor_actions(self.actor, obs, deterministic)
        with torch.inference_mode():
            return self.actor(obs)


def load_policy(
    url: str,
    options: dict | None = None,
    log: Callable[[str], None] = lambda line: None,
    not_a_file: str | None = None,
) -> Policy:
    """The policy at ``url`` (see the module docstring); UserError if nothing verified or no policy is there.

    ``options`` are fsspec storage options; ``log`` hears about newer checkpoints skipped because they do not verify;
    ``not_a_file``: where a file (an exported policy) will not do, why and what to pass instead.
    """
    try:
        if snapshots.parse_snapshot_url(url) is not None:
            storage, step, manifest = snapshots.open_snapshot(url, options)
            state = read_verified(storage, step, snapshots.ACTOR, manifest)
        elif (file := _policy_file(url, options)) is not None:
            if not_a_file is not None:
                raise UserError(f"{file[1]} is a file: {not_a_file}")
            return policy_from_file(*file)
        else:
            storage, step, manifest = resolve_checkpoint_url(url, options, log)
            _refuse_packed(storage.where(step_dir(step)), manifest)
            common = read_verified(storage, step, COMMON, manifest)
            # a distillation checkpoint holds the student (and the teacher it learned from): the student is the policy
            state = common.get("student_state_dict", common.get("actor_state_dict"))
    except CorruptCheckpoint as exc:
        raise UserError(f"{url} does not verify ({exc}): pick another step") from None
    config = config_from_dict(manifest["config"])
    source = storage.where(step_dir(step))
    actor = _actor(config, state, source)
    if (ceiling := build_noise_ceiling(config)) is not None:  # --stochastic samples with the noise of its step
        ceiling.apply(actor.distribution, step)
    return Policy(actor, config, source, step, manifest, manifest["state_sha256"])


def _refuse_packed(where: str, manifest: dict) -> None:
    written = manifest.get("state_format")
    if written in PACKED_STATE_FORMATS:
        raise UserError(
            f"{where} is in ftrain 0.1's packed format (state format {written}), which this ftrain no longer reads: "
            f"load it with the ftrain that wrote it ({manifest.get('versions')})"
        )


def _policy_file(url: str, options: dict | None) -> tuple[bytes, str] | None:
    """The content and printable URL of ``url`` if it names a file (not a checkpoint step or a directory); a file of
    a policy snapshot (its ``policy.onnx``) checked against the snapshot's manifest, as the snapshot would be."""
    if parse_checkpoint_url(url)[1] is not None:
        return None
    storage = Storage.open(url, options)
    if not storage.fs.isfile(storage.root):
        return None
    parent, name = (storage.root if storage.is_local else url).rstrip("/").rpartition("/")[::2]
    if parent and snapshots.parse_snapshot_url(parent) is not None:
        view, step, manifest = snapshots.open_snapshot(parent, options)
        return read_verified_bytes(view, step, name, manifest), storage.url
    return storage.read(""), storage.url


def _actor(config: Config, state: dict, source: str) -> torch.nn.Module:
    """The actor of ``config`` with the learned ``state`` (of ``source``); the environment tells its observation and
    action shapes. UserError if they are not those it was trained on (the env's code, model or kwargs changed)."""
    env = make_env(config.env)
    try:
        obs = TensorDict({OBS_GROUP: torch.zeros(1, *env.observation_space.shape)}, batch_size=[1])
        actor = build_actor(config, obs, env.action_space.shape[0])
    finally:
        env.close()
    try:
        actor.load_state_dict(state)
    except RuntimeError as error:
        mismatch = load_error_line(error)
        raise UserError(
            f"{source} does not fit env.id={config.env.id} as it is now: {mismatch}: {CHANGED_ENV}"
        ) from None
    return actor.eval()


def check_fits(policy: Policy, env) -> None:
    """UserError if ``env`` observes otherwise than ``policy`` was trained to (an exported file records its size)."""
    size = env.observation_space.shape[0]
    if policy.obs_dim is not None and policy.obs_dim != size:
        raise UserError(
            f"{policy.source} does not fit env.id={policy.config.env.id} as it is now: it takes {policy.obs_dim} "
            f"observations, the env gives {size}: {CHANGED_ENV}"
        )


CHANGED_ENV = "the env's code, model file or env.kwargs changed since it was trained: use the env it was trained on"


def policy_from_file(data: bytes, where: str) -> Policy:
    """An exported policy file; UserError if it is not one."""
    fix = "pass a file written by ftrain export, a checkpoint or a run's storage"
    if data.startswith(b"PK"):  # a zip archive: TorchScript, or some other torch file that torch.jit.load refuses
        extra = {METADATA: ""}
        try:
            with torchscript_deprecation_ignored():
                actor = torch.jit.load(io.BytesIO(data), map_location="cpu", _extra_files=extra)
        except RuntimeError as exc:
            reason = str(exc).strip().splitlines()[0].split(". ")[0]
            raise UserError(f"{where} is not a TorchScript policy ({reason}): {fix}") from None
        metadata, fmt = extra[METADATA], "torchscript"
    else:
        import onnx
        from google.protobuf.message import DecodeError

        try:
            model = onnx.load_from_string(data)
        except DecodeError:
            raise UserError(f"{where} is neither a TorchScript nor an ONNX file: {fix}") from None
        metadata, fmt = {prop.key: prop.value for prop in model.metadata_props}.get(METADATA, ""), "onnx"
    if not metadata:
        raise UserError(f"{where} is a {fmt} model but not an ftrain policy (no ftrain metadata): {fix}")
    if fmt == "onnx":
        actor = _OnnxActor(data)
    meta = json.loads(metadata)
    config = config_from_dict(meta["config"])
    digest = hashlib.sha256(data).hexdigest()
    return Policy(actor, config, where, meta["step"], None, digest, exported=fmt, obs_dim=meta.get("obs_dim"))


@contextlib.contextmanager
def torchscript_deprecation_ignored() -> Iterator[None]:
    """torch 2.13 deprecates TorchScript (and the ONNX exporter built on it): the formats asked for here."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield


class _OnnxActor:
    """An ONNX policy run by onnxruntime, called like the TorchScript one."""

    def __init__(self, data: bytes) -> None:
        try:
            import onnxruntime
        except ImportError:
            raise UserError("running an ONNX policy needs onnxruntime: pip install 'ftrain[export]'") from None
        self.session = onnxruntime.InferenceSession(data, providers=["CPUExecutionProvider"])

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.from_numpy(self.session.run(None, {"obs": obs.numpy()})[0])
