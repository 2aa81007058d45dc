"""Bad input to play and export, refused in one line before any rollout: no trained policy needed, since the checks
come before the policy is touched (a stand-in that has only what naming the export's path reads)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from ftrain.config import check_writable
from ftrain.errors import UserError
from ftrain.policy import export as export_module
from ftrain.policy.export import export
from ftrain.policy.play import play

from helpers import child_env

UNWRITABLE = {
    "a directory that takes no new files": (
        Path("/proc/x.onnx"),
        "(/proc takes no new file: No such file or directory)",
    ),
    "a directory missing under one that takes none": (
        Path("/proc/nope/x.onnx"),
        "(/proc takes no new file: No such file or directory)",
    ),
}


def unwritable(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """Paths that cannot be written, with what the refusal says about each."""
    notes = tmp_path / "notes.txt"
    notes.write_text("kept\n")
    return {
        **UNWRITABLE,
        "a file in place of a directory": (notes / "x.onnx", f"({notes}: Not a directory)"),
    }


def test_a_path_that_cannot_be_written_is_one_line_naming_it_and_the_flag(tmp_path) -> None:
    for case, (path, reason) in unwritable(tmp_path).items():
        with pytest.raises(UserError) as refused:
            check_writable(path, "-o")
        message = str(refused.value)
        assert message == f"cannot write {path} {reason}: pass -o a path you can write to", case
    assert (tmp_path / "notes.txt").read_text() == "kept\n"


def test_a_writable_path_passes_and_is_left_as_it_was(tmp_path) -> None:
    existing = tmp_path / "policy.onnx"
    existing.write_bytes(b"an older export")
    check_writable(existing, "-o")
    assert existing.read_bytes() == b"an older export"
    check_writable(tmp_path / "new" / "deeper" / "policy.onnx", "-o")  # made by the export, not by the check
    assert sorted(tmp_path.iterdir()) == [existing]


def test_export_refuses_an_unwritable_output_before_playing_episodes(tmp_path, monkeypatch) -> None:
    def rollout(policy: object) -> None:
        raise AssertionError("the export played the policy's episodes before checking its output")

    monkeypatch.setattr(export_module, "sample_observations", rollout)
    policy = SimpleNamespace(
        source=f"{tmp_path}/run/checkpoints/step-000000008", step=8, config=SimpleNamespace(name="r")
    )
    for path, reason in unwritable(tmp_path).values():
        message = f"cannot write {path} {reason}: pass -o a path you can write to"
        with pytest.raises(UserError, match=f"^{re.escape(message)}$"):
            export(policy, "onnx", path)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"seed": -1}, "--seed -1 is out of range: use a seed from 0 to 4294967295"),
        ({"seed": 2**32}, "--seed 4294967296 is out of range: use a seed from 0 to 4294967295"),
        ({"seed": 2**32 - 1, "episodes": 2}, "--seed 4294967295 is out of range: use a seed from 0 to 4294967294"),
        (
            {"video": "/proc/x.mp4"},
            "cannot write /proc/x.mp4 (/proc takes no new file: No such file or directory): pass --video a path",
        ),
        (
            {"video": "/proc/nope/x.gif"},
            "cannot write /proc/nope/x.gif (/proc takes no new file: No such file or directory): pass --v",
        ),
    ],
)
def test_play_refuses_before_it_makes_an_env(kwargs: dict, message: str) -> None:
    with pytest.raises(UserError) as refused:
        play(object(), **kwargs)  # type: ignore[arg-type]  # touched only after the checks
    assert message in str(refused.value)


def test_the_commands_refuse_their_options_before_torch_is_imported_or_the_policy_looked_up(tmp_path) -> None:
    """``ftrain play`` and ``export`` with options they cannot take, on a URL that does not exist: the option's line
    (not the URL's), exit 2, and torch never imported (its import is seconds; a remote policy's download more)."""
    missing = str(tmp_path / "no-run")
    cases = {
        "--episodes 0: play at least 1 episode": ["play", missing, "--episodes", "0"],
        "--seed -1 is out of range": ["play", missing, "--seed", "-1"],
        "video 'x.avi' must end in .mp4 or .gif": ["play", missing, "--video", "x.avi"],
        "-o x.txt: onnx policy files end in .onnx": ["export", missing, "--format", "onnx", "-o", "x.txt"],
        "cannot write /proc/x.pt": ["export", missing, "--format", "torchscript", "-o", "/proc/x.pt"],
        "export needs --format torchscript or onnx, or -o a file ending in .pt or .onnx": ["export", missing],
        "-o x.txt: policy files end in .pt or .onnx: use -o x.pt or -o x.onnx": ["export", missing, "-o", "x.txt"],
    }
    script = (
        "import json, sys\nfrom ftrain.cli import main\n"
        "codes = [main(argv) for argv in json.loads(sys.argv[1])]\n"
        "print(json.dumps([codes, 'torch' in sys.modules]))"
    )
    result = subprocess.run(
        [sys.executable, "-c", script, json.dumps(list(cases.values()))],
        cwd=tmp_path,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    codes, torch_imported = json.loads(result.stdout.splitlines()[-1])
    lines = result.stderr.splitlines()
    assert codes == [2] * len(cases) and not torch_imported, result.stderr
    assert len(lines) == len(cases), lines
    for expected, line in zip(cases, lines, strict=True):
        assert line.startswith("ftrain: error: ") and expected in line, line
