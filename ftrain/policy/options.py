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


def export_format(fmt: str | None, path: str | Path | None) -> str:
    """The format ``export`` writes: ``fmt`` (``--format``), or else the one the file ``path`` (``-o``) ends in.
    UserError for a format it does not write, or an output ``path`` it cannot take (a file named for it: a directory,
    where the file's name comes from the policy, is checked once that is known)."""
    if fmt is not None and fmt not in POLICY_FORMATS:
        raise UserError(f"unknown policy format {fmt!r}: use {' or '.join(POLICY_FORMATS)}")
    suffixes = " or ".join(SUFFIXES.values())
    if path is None or names_a_directory(path):
        if fmt is None:
            raise UserError(f"export needs --format {' or '.join(POLICY_FORMATS)}, or -o a file ending in {suffixes}")
        return fmt
    path = Path(path)
    named = next((named for named, suffix in SUFFIXES.items() if path.suffix == suffix), None)
    if fmt is None and named is None:
        raise UserError(
            f"-o {path}: policy files end in {suffixes}: use -o {path.with_suffix('.pt')} or -o "
            f"{path.with_suffix('.onnx')}"
        )
    if fmt not in (None, named):  # ``-o README.md`` would write over a file of another kind
        other = next(other for other in POLICY_FORMATS if other != fmt)
        raise UserError(
            f"-o {path}: {fmt} policy files end in {SUFFIXES[fmt]}: use -o {path.with_suffix(SUFFIXES[fmt])}, "
            f"a directory, or --format {other} for a {SUFFIXES[other]} file"
        )
    check_output(path, "-o")
    return fmt or named


def names_a_directory(path: str | Path) -> bool:
    """Whether ``-o`` names where the export goes (a directory, or one to make: it ends in ``/``), not its file."""
    return Path(path).is_dir() or str(path).endswith("/")
