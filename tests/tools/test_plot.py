"""``ftrain plot`` on a real run that lost its newest checkpoint and resumed from an older one."""

from __future__ import annotations

import csv
import itertools
import math
import random
import shutil
import struct
from pathlib import Path

import pytest

from ftrain.cli import main
from ftrain.supervise.events import EventLog
from ftrain.tools.plot import curve, gaps, plot_run, read_metrics

from helpers import run_train

PANELS = ["Episode return", "Episode length", "Losses", "Throughput"]


pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def resumed(tmp_path_factory) -> Path:
    """Iterations 1-6, checkpoint 6 lost, then 5-8 again from checkpoint 4."""
    run = tmp_path_factory.mktemp("plot") / "run"
    run_train(run, "iterations=6", "eval.every=2", "eval.episodes=1")
    shutil.rmtree(run / "checkpoints" / "step-000000006")
    run_train(run, "iterations=8", "eval.every=2", "eval.episodes=1")
    return run


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR", f"{path} is not a PNG"
    return struct.unpack(">II", data[16:24])


def test_metrics_keep_one_row_per_iteration_from_the_run_that_continued(resumed) -> None:
    with (resumed / "metrics.csv").open() as file:
        raw = list(csv.DictReader(file))
    assert [int(row["iteration"]) for row in raw] == [1, 2, 3, 4, 5, 6, 7, 8]
    assert [row["resumed_from"] for row in raw] == ["", "", "", "", "4", "", "", ""]
    assert [row["config_change"] for row in raw] == [""] * 8
    columns, resumed_from, changes = read_metrics(resumed)
    assert columns["iteration"] == [1, 2, 3, 4, 5, 6, 7, 8]
    assert columns["steps_per_s"] == [float(row["steps_per_s"]) for row in raw]
    assert resumed_from == [4] and changes == {}


def test_files_of_older_versions_keep_the_last_row_of_each_iteration(resumed, tmp_path) -> None:
    with (resumed / "metrics.csv").open() as file:
        rows = list(csv.DictReader(file))
    run = tmp_path / "old"
    run.mkdir()
    with (run / "metrics.csv").open("w", newline="") as file:
        writer = csv.DictWriter(file, [name for name in rows[0] if name != "resumed_from"], extrasaction="ignore")
        writer.writeheader()
        writer.writerows([*rows[:6], {**rows[4], "steps_per_s": "1"}, *rows[5:]])  # 5, 6 twice, the last rows win
    columns, resumed_from, changes = read_metrics(run)
    assert columns["iteration"] == [1, 2, 3, 4, 5, 6, 7, 8] and columns["steps_per_s"][4] == 1.0
    assert resumed_from == [4] and changes == {}


def test_rows_cut_short_or_run_together_are_skipped_and_counted(resumed, tmp_path, capsys) -> None:
    """What a crash mid-write leaves (a row cut short, the next run's row glued to it) and a row with bytes that are
    not text, and rows whose iteration is not a whole number are skipped and counted, as training's own reader of the
    file drops them (a row's iteration refused the whole plot)."""
    lines = (resumed / "metrics.csv").read_text().splitlines(keepends=True)
    run = tmp_path / "damaged"
    run.mkdir()
    glued = lines[3][: len(lines[3]) // 2] + lines[4]  # iteration 3 cut short, iteration 4 run into it
    not_numbered = [f"{iteration}{lines[8][1:]}" for iteration in ("zz", "\u00b2", "", "-8", "8.0", "9" * 5000)]
    text = "".join([*lines[:3], glued, *lines[5:], "garbage,,,\n", *not_numbered]).encode()
    (run / "metrics.csv").write_bytes(text.replace(b"\n5,", b"\n5,\xff\xfe", 1))  # row 5: bytes that are not text
    columns, _, _ = read_metrics(run)
    assert columns["iteration"] == [1, 2, 6, 7, 8]
    assert (
        capsys.readouterr().err
        == f"ftrain plot: {run / 'metrics.csv'}: skipped 9 damaged rows (lines 4, 5, 9, 10, 11 and 4 more)\n"
    )


def test_plot_marks_a_resume_that_was_no_restart(resumed, tmp_path) -> None:
    plot = plot_run(resumed, tmp_path / "curves.png")
    assert plot.panels == PANELS and (plot.restarts, plot.resumes) == ([], [4])
    assert plot.title == "run: 8 iterations, 1 resume (dotted): at the step resumed from", plot.title
    assert png_size(plot.path) == (1200, 800)
    assert plot.path.stat().st_size > 30_000, "a PNG with four panels of curves and text"


def test_iterations_missing_from_the_file_break_the_curves_and_are_named(resumed, tmp_path, capsys) -> None:
    """Iterations 3-4 and 7 have no rows (a start with log.csv=false): one line names them, and no curve is drawn
    across them."""
    lines = (resumed / "metrics.csv").read_text().splitlines(keepends=True)
    run = tmp_path / "gaps"
    run.mkdir()
    (run / "metrics.csv").write_text("".join([*lines[:3], *lines[5:7], lines[8]]))
    plot = plot_run(run, tmp_path / "curves.png")
    assert plot.missing == [(3, 4), (7, 7)]
    assert f"{run / 'metrics.csv'} has no rows for iterations 3-4, 7 (logged with log.csv=false, or lost)" in (
        capsys.readouterr().err
    )


def test_a_run_in_which_no_episode_ended_has_no_empty_panel(resumed, tmp_path) -> None:
    """HalfCheetah's episodes last 1,000 steps, 62 iterations of the shipped config: a shorter run logs no episode
    return or length (NaN in every row), which drew an empty panel."""
    rows = list(csv.DictReader((resumed / "metrics.csv").open()))
    run = tmp_path / "short"
    run.mkdir()
    with (run / "metrics.csv").open("w", newline="") as file:
        writer = csv.DictWriter(file, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(row | {"mean_return": "nan", "mean_length": "nan"} for row in rows)
    assert plot_run(run, tmp_path / "curves.png").panels == ["Episode return", "Losses", "Throughput"]  # evaluations


def test_a_curve_never_joins_two_points_across_a_missing_iteration() -> None:
    """Generated files (seeded): which iterations have rows, and which rows have a value in the column (an
    evaluation's, every few rows): every value is drawn, and the line between two drawn points spans no iteration
    the file lacks."""
    checked = broken = 0
    for case in range(300):
        draw = random.Random(case)
        iterations = sorted(draw.sample(range(1, 40), draw.randint(1, 30)))
        values = [math.nan if draw.random() < 0.4 else float(x) for x in iterations]
        xs, ys = curve(iterations, values, gaps(iterations))
        drawn = [x for x, y in zip(xs, ys, strict=True) if not math.isnan(y)]
        assert drawn == [x for x, v in zip(iterations, values, strict=True) if not math.isnan(v)]
        present = set(iterations)
        for (x0, y0), (x1, y1) in itertools.pairwise(zip(xs, ys, strict=True)):
            if not (math.isnan(y0) or math.isnan(y1)):  # a line is drawn between them
                assert all(x in present for x in range(int(x0), int(x1) + 1)), (case, iterations, x0, x1)
        checked += 1
        broken += bool(gaps(iterations))
    print(f"{checked} generated curves ({broken} with iterations missing): no line across a missing iteration")
    assert broken >= 100


def test_plot_adds_the_supervisors_restarts(resumed, tmp_path) -> None:
    run = tmp_path / "supervised"
    run.mkdir()
    shutil.copy(resumed / "metrics.csv", run)
    events = EventLog(run / "events.jsonl", None)
    events("start", attempt=1)
    events("resumed", attempt=1, step=None)  # a fresh start
    events("restart", attempt=2, restarts=1)
    events("resumed", attempt=2, step=2)
    events("restart", attempt=3, restarts=2)
    events("resumed", attempt=3, step=None)  # a crash before the first checkpoint: restarted from the start
    events("restart", attempt=4, restarts=3)
    events("resumed", attempt=4, step=2)  # a second restart from step 2: counted, on the same line
    with (run / "events.jsonl").open("a") as file:  # damaged since: skipped, a step of another type as none
        file.write('[1, 2]\nnull\n{"event": "restart"}\n{"event": "resumed", "step": "4"}\n' + "[" * 5000 + "\n")
        file.write('{"time": 1.0, "event": "resu')  # cut short when the supervisor itself was killed
    plot = plot_run(run)
    assert (plot.restarts, plot.resumes) == ([0, 0, 2, 2], [4])
    assert plot.title == "supervised: 8 iterations, 4 restarts (dashed), 1 resume (dotted): at the step resumed from"
    assert (run / "curves.png").is_file()


def test_cli(resumed, tmp_path, capsys) -> None:
    out = tmp_path / "c.png"
    assert main(["plot", str(resumed), "-o", str(out)]) == 0
    assert png_size(out) == (1200, 800)
    assert main(["plot", str(tmp_path / "nothing")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "metrics.csv does not exist: pass a run's log directory" in err
    assert main(["plot", str(resumed), "-o", str(tmp_path / "c.txt")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "c.txt: not a picture file matplotlib writes: end it in .png, .svg or .pdf" in err
    assert main(["plot", str(resumed), "-o", "/proc/c.png"]) == 2
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1
        and "cannot write /proc/c.png (/proc takes no new file: No such file or directory): pass -o a" in err
    )
    assert main(["plot", str(resumed), "-o", str(tmp_path)]) == 0 and png_size(tmp_path / "curves.png") == (1200, 800)
    assert main(["plot", str(resumed), "-o", f"{tmp_path / 'new'}/"]) == 0  # a folder not there yet: made, as export's
    assert png_size(tmp_path / "new" / "curves.png") == (1200, 800) and not (tmp_path / "new.png").exists()
    capsys.readouterr()
    assert main(["plot", str(resumed / "metrics.csv"), "-o", str(tmp_path / "curves")]) == 0  # the file, no suffix
    assert capsys.readouterr().out == f"wrote {tmp_path / 'curves.png'}\n" and not (tmp_path / "curves").exists()
    step = resumed / "checkpoints" / "step-000000008"  # a step, as play and export take it: its run's curves
    assert main(["plot", str(step), "-o", str(tmp_path / "step.png")]) == 0 and png_size(tmp_path / "step.png")
    assert capsys.readouterr().err == f"ftrain plot: {step} is step 8 of {resumed}: plotting {resumed}\n"
