"""Bad input to ``ftrain plot`` and ``ftrain bench``: one line naming it and the fix, exit code 2, nothing run."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from ftrain.cli import main
from ftrain.errors import UserError
from ftrain.tools import bench
from ftrain.tools.plot import plot_run

METRICS = "iteration,mean_return,resumed_from\n1,-3.5,\n2,-1.25,\n"


def refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """``ftrain argv``'s one line of error, checked to be one line with exit code 2."""
    assert main(argv) == 2, argv
    err = capsys.readouterr().err
    assert err.startswith("ftrain: error: ") and err.count("\n") == 1, err
    return err


def a_run(directory: Path, metrics: bytes) -> Path:
    directory.mkdir()
    (directory / "metrics.csv").write_bytes(metrics)
    return directory


@pytest.mark.parametrize(
    ("metrics", "message"),
    [
        (b"a,b,c\n1,2,3\n", "metrics.csv has no iteration column (its columns: a, b, c): pass a run's log directory"),
        (b"iteration,x\n1,\xff\xfe\n", "metrics.csv holds no row but 1 damaged one: pass a run's log directory"),
        (b"iteration,resumed_from\n1,one\n2,2.5\n", "metrics.csv holds no row but 2 damaged ones: pass a run's log"),
    ],
    ids=["no iteration column", "not UTF-8", "steps not numbers"],
)
def test_a_malformed_metrics_file_is_one_line_naming_it(tmp_path, capsys, metrics: bytes, message: str) -> None:
    run = a_run(tmp_path / "run", metrics)
    assert f"{run}/{message}" in refused(["plot", str(run)], capsys)
    assert sorted(path.name for path in run.iterdir()) == ["metrics.csv"]


def test_an_output_that_cannot_be_written_is_one_line_naming_it(tmp_path, capsys) -> None:
    run = a_run(tmp_path / "run", METRICS.encode())
    notes = tmp_path / "notes.txt"
    notes.write_text("kept\n")
    for output, reason in [
        ("/proc/c.png", "/proc takes no new file: No such file or directory"),
        ("/proc/nope/c.png", "/proc takes no new file: No such file or directory"),
        (f"{notes}/c.png", f"{notes}: Not a directory"),
    ]:
        err = refused(["plot", str(run), "-o", output], capsys)
        assert f"cannot write {output} ({reason}): pass -o a path you can write to" in err
    assert notes.read_text() == "kept\n"
    plot = plot_run(run, tmp_path / "new" / "c.png")  # a directory still to be made is fine
    assert plot.path.stat().st_size > 0 and plot.panels == ["Episode return"]


@pytest.mark.parametrize("argv", [["--iterations", "0"], ["--iterations", "-1", "--settings", "fixed"]])
def test_bench_needs_an_iteration_to_time(argv: list[str], capsys, monkeypatch) -> None:
    def case(*args: object, **kwargs: object) -> None:
        raise AssertionError("a case ran")

    monkeypatch.setattr(bench.subprocess, "run", case)
    err = refused(["bench", *argv], capsys)
    assert f"--iterations {argv[1]}: time at least 1 iteration per case" in err
    with pytest.raises(UserError, match="time at least 1 iteration"):
        bench.run_benchmark(0, ["config"])


def test_bench_cases_leave_no_mujoco_log_in_the_working_directory(tmp_path) -> None:
    """The raw case steps gymnasium's own HalfCheetah, whose model MuJoCo warns about (settotalmass)."""
    done = subprocess.run(bench.case_command("raw", 1, "fixed"), cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert float(done.stdout.splitlines()[-1]) > 0
    assert list(tmp_path.iterdir()) == []
