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
FORMATS = {suffix: fmt for fmt, suffix in SUFFIXES.items()}
"""The format each suffix names (``-o policy.onnx``)."""


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
    if path is not None and not names_a_directory(path):
        return _file_format(fmt, Path(path))
    if fmt is None:
        where = "export" if path is None else f"-o {path} is a directory: export into it"
        raise UserError(
            f"{where} needs --format {' or '.join(POLICY_FORMATS)}, or -o a file ending in {' or '.join(FORMATS)}"
        )
    return fmt


def _file_format(fmt: str | None, path: Path) -> str:
    """The format of the file ``path`` that ``export -o`` writes: the one its suffix names, which ``fmt`` must not
    contradict (``-o README.md`` would write over a file of another kind)."""
    named = FORMATS.get(path.suffix.lower())
    if fmt is None and named is None:
        raise UserError(
            f"-o {path}: policy files end in {' or '.join(FORMATS)}: use -o {path.with_suffix('.pt')} or -o "
            f"{path.with_suffix('.onnx')}"
        )
    if fmt is not None and named != fmt:
        other = next(other for other in POLICY_FORMATS if other != fmt)
        instead = f", or --format {other}" if named == other else ""
        raise UserError(
            f"-o {path}: {fmt} policy files end in {SUFFIXES[fmt]}: use -o {path.with_suffix(SUFFIXES[fmt])} or a "
            f"directory{instead}"
        )
    check_output(path, "-o")
    return named


def names_a_directory(path: str | Path) -> bool:
    """Whether ``-o`` names where the export goes (a directory, or one to make: it ends in ``/``), not its file."""
    return Path(path).is_dir() or str(path).endswith("/")
