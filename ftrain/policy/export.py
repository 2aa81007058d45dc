"""Export: a policy as a self-contained, verified TorchScript or ONNX file."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

from ftrain.ckpt.steps import check_output
from ftrain.config import default_log_dir
from ftrain.errors import UserError
from ftrain.policy.load import METADATA, Policy, policy_from_file, torchscript_deprecation_ignored
from ftrain.policy.options import SUFFIXES, export_format, names_a_directory
from ftrain.policy.robot import make_env
from ftrain.policy.rollout import rollout
from ftrain.progress import Progress

TOLERANCE = 1e-5
"""Largest difference (absolute and relative) allowed between an export's actions and the actor's."""


class ExportMismatch(RuntimeError):
    """An exported policy does not reproduce the actor it was exported from (a bug, never bad input)."""


def output_path(path: str | Path | None, directory: Path, name: str) -> Path:
    """Where ``export`` writes: ``path``, or ``name`` in it where it names a directory (in ``directory`` where
    None)."""
    if path is None or names_a_directory(path):
        return Path(path or directory) / name
    return Path(path)


def encode(policy: Policy, fmt: str, observations: torch.Tensor) -> bytes:
    """``policy`` as a self-contained ``fmt`` file, verified: loaded back and run on ``observations [N, obs_dim]``,
    its actions must match the actor's deterministic ones (ExportMismatch otherwise)."""
    export_format(fmt, None)
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
    actual = policy_from_file(data, f"exported {fmt} policy").act(observations)
    if not torch.allclose(actual, expected, atol=TOLERANCE, rtol=TOLERANCE):
        error = (actual - expected).abs().max().item()
        raise ExportMismatch(
            f"the exported {fmt} policy does not reproduce the actor of {policy.source}: actions differ by up to "
            f"{error:.3g} on {len(observations)} observations (tolerance {TOLERANCE})"
        )
    return data


def _torchscript(actor: torch.nn.Module, metadata: str) -> bytes:
    buffer = io.BytesIO()
    with torchscript_deprecation_ignored():
        torch.jit.save(torch.jit.script(actor.as_jit().eval()), buffer, _extra_files={METADATA: metadata})
    return buffer.getvalue()


def _onnx(actor: torch.nn.Module, metadata: str) -> bytes:
    """ONNX with a dynamic batch axis named ``batch`` in its inputs and outputs, by torch's current exporter
    (``torch.export``, ``dynamo=True``: the TorchScript-based one is deprecated). It takes 1.5-3 s per export here,
    against 30 ms for the old one."""
    import onnx

    model = actor.as_onnx(verbose=False).eval()
    buffer = io.BytesIO()
    batch = torch.export.Dim("batch")  # Dim.DYNAMIC would name it as the exporter's symbols go (s77)
    with _exporter_quiet():
        torch.onnx.export(
            model,
            model.get_dummy_inputs(),
            buffer,
            input_names=model.input_names,
            output_names=model.output_names,
            dynamic_shapes=tuple({0: batch} for _ in model.input_names),
            opset_version=18,
            dynamo=True,
            verbose=False,
        )
    proto = onnx.load_from_string(buffer.getvalue())
    onnx.helper.set_model_props(proto, {METADATA: metadata})
    return proto.SerializeToString()


@contextlib.contextmanager
def _exporter_quiet() -> Iterator[None]:
    """The exporter's progress lines and its notes about optional packages (torchvision's operators) are not the
    user's business: an export says what it wrote, once."""
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            yield
    finally:
        logger.setLevel(level)


def sample_observations(policy: Policy, episodes: int = 3, seed: int = 0) -> torch.Tensor:
    """Real observations ``[N, obs_dim]``: every one the policy sees in ``episodes`` deterministic episodes."""
    seen: list[np.ndarray] = []
    env = make_env(policy.config.env)
    try:
        rollout(env, policy.act, episodes, seed, on_observation=seen.append)
    finally:
        env.close()
    return torch.as_tensor(np.stack(seen), dtype=torch.float32)


def export(policy: Policy, fmt: str | None, path: str | Path | None = None) -> Path:
    """Write ``policy`` as a verified ``fmt`` file (None: the format ``path`` ends in) to ``path`` and say so on
    stdout. By default next to the run, in ``<run>/exports/<run name>-step-<N>.pt``/``.onnx`` (for a run on S3, in
    its local log directory ``runs/<name>``), not in the working directory."""
    fmt = export_format(fmt, path)
    run = policy.source.rstrip("/").rsplit("/", 2)[0]  # the source is <run>/checkpoints/step-N or <run>/policies/...
    name = f"{policy.config.name}-step-{policy.step}{SUFFIXES[fmt]}"
    path = output_path(path, Path(default_log_dir(run, policy.config.name)) / "exports", name)
    check_output(path, "-o")
    progress = Progress()
    progress.show("export: playing the policy's episodes that the export is checked on...")
    try:
        observations = sample_observations(policy)
        progress.show(f"export: writing the {fmt} file, checking its actions on {len(observations):,} observations...")
        data = encode(policy, fmt, observations)
    finally:
        progress.clear()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    print(
        f"wrote {path}: {fmt} policy of step {policy.step} from {policy.source}, {len(data):,} bytes, "
        f"sha256 {hashlib.sha256(data).hexdigest()}; its actions match the actor's on {len(observations)} "
        "observations"
    )
    return path
