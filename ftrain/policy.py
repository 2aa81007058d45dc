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
import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ftrain import checkpoint
from ftrain.algorithm import build_actor
from ftrain.config import Config, config_from_dict
from ftrain.envs import MujocoVecEnv
from ftrain.errors import UserError
from ftrain.evaluation import actor_actions, make_env, rollout
from ftrain.storage import Storage

FORMATS = ("torchscript", "onnx")
SUFFIXES = {"torchscript": ".pt", "onnx": ".onnx"}
METADATA = "ftrain.json"
"""Key of the metadata in an exported file: a TorchScript extra file, an ONNX metadata property."""
TOLERANCE = 1e-5
"""Largest difference (absolute and relative) allowed between an export's actions and the actor's."""
VIDEO_SUFFIXES = (".mp4", ".gif")


class ExportMismatch(RuntimeError):
    """An exported policy does not reproduce the actor it was exported from (a bug, never bad input)."""


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

    def act(self, obs: torch.Tensor, deterministic: bool = True) -> torch.Tensor:
        """Actions for observations ``[N, obs_dim]``; an exported policy has only its deterministic ones."""
        if self.exported is None:
            return actor_actions(self.actor, obs, deterministic)
        with torch.inference_mode():
            return self.actor(obs)


def load_policy(url: str, options: dict | None = None, log: Callable[[str], None] = lambda line: None) -> Policy:
    """The policy at ``url`` (see the module docstring); UserError if nothing verified or no policy is there.

    ``options`` are fsspec storage options; ``log`` hears about newer checkpoints skipped because they do not verify.
    """
    from ftrain import snapshots  # it builds on this module to export snapshots

    try:
        if snapshots.parse_snapshot_url(url) is not None:
            storage, step, manifest = snapshots.open_snapshot(url, options)
            state = checkpoint.read_verified(storage, step, snapshots.ACTOR, manifest)
        elif (file := _policy_file(url, options)) is not None:
            return _from_file(*file)
        else:
            storage, step, manifest = checkpoint.resolve_checkpoint_url(url, options, log)
            learned = checkpoint.read_verified(storage, step, checkpoint.COMMON, manifest)["learned"]
            # a distillation checkpoint holds the student (and the teacher it learned from): the student is the policy
            state = learned.get("student_state_dict", learned.get("actor_state_dict"))
    except checkpoint.CorruptCheckpoint as exc:
        raise UserError(f"{url} does not verify ({exc}): pick another step") from None
    config = config_from_dict(manifest["config"])
    source = storage.where(checkpoint.step_dir(step))
    return Policy(_actor(config, state), config, source, step, manifest, manifest["state_sha256"])


def _policy_file(url: str, options: dict | None) -> tuple[bytes, str] | None:
    """The content and printable URL of ``url`` if it names a file (not a checkpoint step or a directory)."""
    if checkpoint.parse_checkpoint_url(url)[1] is not None:
        return None
    storage = Storage.open(url, options)
    return (storage.read(""), storage.url) if storage.fs.isfile(storage.root) else None


def _actor(config: Config, state: dict) -> torch.nn.Module:
    """The actor of ``config`` with the learned ``state``; the environment tells its observation and action shapes."""
    env = MujocoVecEnv(config.env.id, 1, 0, config.env.kwargs)
    try:
        actor = build_actor(config, env.get_observations(), env.num_actions)
    finally:
        env.close()
    actor.load_state_dict(state)
    return actor.eval()


def _from_file(data: bytes, where: str) -> Policy:
    """An exported policy file; UserError if it is not one."""
    fix = "pass a file written by ftrain export, a checkpoint or a run's storage"
    if data.startswith(b"PK"):  # a zip archive: TorchScript, or some other torch file that torch.jit.load refuses
        extra = {METADATA: ""}
        try:
            with _torchscript_deprecation_ignored():
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
    return Policy(actor, config, where, meta["step"], None, hashlib.sha256(data).hexdigest(), exported=fmt)


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


# --- export ----------------------------------------------------------------------------------------------------


def check_format(fmt: str) -> None:
    if fmt not in FORMATS:
        raise UserError(f"unknown policy format {fmt!r}: use {' or '.join(FORMATS)}")


def encode(policy: Policy, fmt: str, observations: torch.Tensor) -> bytes:
    """``policy`` as a self-contained ``fmt`` file, verified: loaded back and run on ``observations [N, obs_dim]``,
    its actions must match the actor's deterministic ones (ExportMismatch otherwise)."""
    check_format(fmt)
    if policy.exported is not None:
        raise UserError(
            f"{policy.source} is an exported {policy.exported} policy: export from a checkpoint, a run's storage "
            "or a policy snapshot"
        )
    metadata = json.dumps(
        {
            "format": fmt,
            "step": policy.step,
            "source": policy.source,
            "state_sha256": policy.digest,
            "obs_dim": int(observations.shape[1]),
            "config": policy.config.public_dict(),
        }
    )
    data = _torchscript(policy.actor, metadata) if fmt == "torchscript" else _onnx(policy.actor, metadata)
    expected = policy.act(observations)
    actual = _from_file(data, f"exported {fmt} policy").act(observations)
    if not torch.allclose(actual, expected, atol=TOLERANCE, rtol=TOLERANCE):
        error = (actual - expected).abs().max().item()
        raise ExportMismatch(
            f"the exported {fmt} policy does not reproduce the actor of {policy.source}: actions differ by up to "
            f"{error:.3g} on {len(observations)} observations (tolerance {TOLERANCE})"
        )
    return data


@contextlib.contextmanager
def _torchscript_deprecation_ignored() -> Iterator[None]:
    """torch 2.13 deprecates TorchScript (and the ONNX exporter built on it): the formats asked for here."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        yield


def _torchscript(actor: torch.nn.Module, metadata: str) -> bytes:
    buffer = io.BytesIO()
    with _torchscript_deprecation_ignored():
        torch.jit.save(torch.jit.script(actor.as_jit().eval()), buffer, _extra_files={METADATA: metadata})
    return buffer.getvalue()


def _onnx(actor: torch.nn.Module, metadata: str) -> bytes:
    """ONNX with a dynamic batch axis, by torch's TorchScript-based exporter: the torch.export-based one (the
    default since torch 2.9) took 0.8-2 s per export here against 30 ms, and snapshots export during training."""
    import onnx

    model = actor.as_onnx(verbose=False).eval()
    buffer = io.BytesIO()
    with _torchscript_deprecation_ignored():
        torch.onnx.export(
            model,
            model.get_dummy_inputs(),
            buffer,
            input_names=model.input_names,
            output_names=model.output_names,
            dynamic_axes={name: {0: "batch"} for name in (*model.input_names, *model.output_names)},
            opset_version=18,
            dynamo=False,
        )
    proto = onnx.load_from_string(buffer.getvalue())
    onnx.helper.set_model_props(proto, {METADATA: metadata})
    return proto.SerializeToString()


def sample_observations(policy: Policy, episodes: int = 3, seed: int = 0) -> torch.Tensor:
    """Real observations ``[N, obs_dim]``: every one the policy sees in ``episodes`` deterministic episodes."""
    seen: list[np.ndarray] = []
    env = make_env(policy.config.env)
    try:
        rollout(env, policy.act, episodes, seed, on_observation=seen.append)
    finally:
        env.close()
    return torch.as_tensor(np.stack(seen), dtype=torch.float32)


def export(policy: Policy, fmt: str, path: str | Path | None = None) -> Path:
    """Write ``policy`` as a verified ``fmt`` file to ``path`` (default ``<run name>-step-<N>.pt``/``.onnx`` in the
    working directory) and say so on stdout."""
    check_format(fmt)
    observations = sample_observations(policy)
    data = encode(policy, fmt, observations)
    path = Path(path or f"{policy.config.name}-step-{policy.step}{SUFFIXES[fmt]}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    print(
        f"wrote {path}: {fmt} policy of step {policy.step} from {policy.source}, {len(data):,} bytes, "
        f"sha256 {hashlib.sha256(data).hexdigest()}; its actions match the actor's on {len(observations)} "
        "observations"
    )
    return path


# --- play ------------------------------------------------------------------------------------------------------


@dataclass
class PlayResult:
    returns: list[float]
    lengths: list[int]
    frames: int
    """Video frames written: one per observation, ``sum(length + 1)`` (0 without a video)."""


def play(
    policy: Policy, episodes: int = 1, deterministic: bool = False, video: str | Path | None = None, seed: int = 0
) -> PlayResult:
    """Roll ``policy`` out for ``episodes`` episodes (seeded ``seed``, ``seed + 1``, ...) in an environment of its
    own; print each return and the mean. ``video`` (``.mp4`` or ``.gif``) renders it headless (MUJOCO_GL=egl)."""
    if episodes < 1:
        raise UserError(f"--episodes {episodes}: play at least 1 episode")
    if video is not None and Path(video).suffix.lower() not in VIDEO_SUFFIXES:
        raise UserError(f"video {str(video)!r} must end in {' or '.join(VIDEO_SUFFIXES)}")
    if video is not None:
        os.environ.setdefault("MUJOCO_GL", "egl")  # read when the first renderer is made: headless, no display
    deterministic = deterministic or policy.exported is not None
    mode = "deterministic (mean) actions" if deterministic else "sampled actions"
    if policy.exported is not None:
        mode += f" (an exported {policy.exported} policy has no others)"
    print(f"playing {policy.source} (step {policy.step}, {policy.config.env.id}) with {mode}")
    torch.manual_seed(seed)
    env = make_env(policy.config.env, render=video is not None)
    writer = None if video is None else _VideoWriter(Path(video), env)
    try:
        results = rollout(
            env,
            lambda obs: policy.act(obs, deterministic),
            episodes,
            seed,
            on_observation=None if writer is None else writer.add_frame,
        )
    finally:
        env.close()
        if writer is not None:
            writer.close()
    for index, episode in enumerate(results, start=1):
        print(f"episode {index}: return {episode.ret:.2f}, length {episode.length}")
    returns = [episode.ret for episode in results]
    print(f"mean return over {episodes} episodes: {np.mean(returns):.2f} (std {np.std(returns):.2f})")
    frames = 0 if writer is None else writer.frames
    if writer is not None:
        height, width = writer.size
        print(f"video: {video} ({frames} frames of {width}x{height} at {writer.fps:g} fps)")
    return PlayResult(returns, [episode.length for episode in results], frames)


class _VideoWriter:
    """Renders the environment at every observation and streams the frames to an mp4 (ffmpeg) or a gif."""

    def __init__(self, path: Path, env) -> None:
        import imageio.v2 as imageio

        self.env = env
        self.fps = float(env.metadata.get("render_fps", 30))
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.suffix.lower() == ".gif":
            self.writer = imageio.get_writer(path, mode="I", duration=1000 / self.fps, loop=0)
        else:
            self.writer = imageio.get_writer(path, fps=self.fps)
        self.frames = 0
        self.size = (0, 0)

    def add_frame(self, obs: np.ndarray) -> None:
        try:
            frame = self.env.render()
        except Exception as exc:  # no usable OpenGL: the error type depends on the backend and what is missing
            raise UserError(
                f"headless rendering failed ({type(exc).__name__}: {exc}): install Debian's Mesa EGL "
                "(apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri) and keep MUJOCO_GL=egl"
            ) from None
        self.writer.append_data(frame)
        self.frames += 1
        self.size = frame.shape[:2]

    def close(self) -> None:
        self.writer.close()
