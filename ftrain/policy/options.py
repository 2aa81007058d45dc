"""The options of ``play`` and ``export``, checked before torch is imported or a policy is loaded (from a remote
storage, maybe): a typo costs milliseconds, not seconds of imports or a download.

May import: ckpt.steps, config, errors (nothing that imports torch).
"""

from __future__ import annotations

from pathlib import Path

from ftrain.ckpt.steps import check_output
from ftrain.config import POLICY_FORMATS, SEEDS
from ftrain.errors import UserError

VIDEO_SUFFIXES = (".mp4", ".gif")
SUFFIXES = {"torchscript": ".pt", "onnx": ".onnx"}
"""The suffix of each export format's files."""


def check_play_options(episodes: int, seed: int, video: str | Path | None) -> None:
    """UserError for options of ``play`` it cannot take."""
    if episodes < 1:
        raise UserError(f"--episodes {episodes}: play at least 1 episode")
    if not 0 <= seed <= SEEDS - episodes:  # the episodes take the seeds seed to seed + episodes - 1
        raise UserError(f"--seed {seed} is out of range: use a seed from 0 to {SEEDS - episodes}")
    if video is not None and Path(video).suffix.lower() not in VIDEO_SUFFIXES:
        raise UserError(f"video {str(video)!r} must end in {' or '.join(VIDEO_SUFFIXES)}")
    if video is not None:
        check_output(Path(video), "--video")


def check_export_options(fmt: str, path: str | Path | None) -> None:
    """UserError for a format ``export`` does not write, or an output ``path`` it cannot take (a file named for it:
    a directory, where the file's name comes from the policy, is checked once that is known)."""
    if fmt not in POLICY_FORMATS:
        raise UserError(f"unknown policy format {fmt!r}: use {' or '.join(POLICY_FORMATS)}")
    if path is None or names_a_directory(path):
        return
    if Path(path).suffix != SUFFIXES[fmt]:  # ``-o README.md`` would write over a file of another kind
        other = next(other for other in POLICY_FORMATS if other != fmt)
        raise UserError(
            f"-o {path}: {fmt} policy files end in {SUFFIXES[fmt]}: use -o {Path(path).with_suffix(SUFFIXES[fmt])}, "
            f"a directory, or --format {other} for a {SUFFIXES[other]} file"
        )
    check_output(Path(path), "-o")


def names_a_directory(path: str | Path) -> bool:
    """Whether ``-o`` names where the export goes (a directory, or one to make: it ends in ``/``), not its file."""
    return Path(path).is_dir() or str(path).endswith("/")
