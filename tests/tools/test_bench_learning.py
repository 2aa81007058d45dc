"""The learning benchmark's per-seed report: what counts as reached, the worst seed and the median."""

import json
import math
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import pytest
from bench_learning import Run, Seeds, reused, seed_table


def run(seed: int, final: float, returns: list[float], every: float = 20_000.0, pace: float = 10.0) -> Run:
    """A run whose evaluations come every ``every`` steps and ``pace`` seconds, returning ``returns``."""
    curve = [(every * (i + 1), pace * (i + 1), value, 0.5 * (i + 1)) for i, value in enumerate(returns)]
    return Run(
        curve=curve,
        seconds=pace * len(returns),
        eval_seconds=0.5 * len(returns),
        steps=1000,
        seed=seed,
        final_return=final,
        episodes=[final - 100.0, final + 100.0],
        load=(0.0, 0.0),
    )


def test_every_seed_is_reported_with_the_median_and_the_worst() -> None:
    runs = [
        run(1, 6_100.0, [3_000.0, 5_200.0, 6_000.0]),  # 5,000 at the second evaluation
        run(2, 5_900.0, [5_100.0, 5_000.0, 6_000.0]),  # at the first
        run(3, 4_400.0, [3_000.0, 4_000.0, 4_900.0]),  # never
    ]
    seeds = Seeds.of("HalfCheetah-v5", runs)
    assert (seeds.reached, seeds.above_zoo, seeds.worst_return) == (2, 2, 4_400.0)
    assert seeds.steps_to == [40_000.0, 20_000.0, math.inf]
    assert seeds.times_to == [20.0, 10.0, math.inf] and seeds.spread == math.inf
    table = seed_table("HalfCheetah-v5", runs).splitlines()
    assert len(table) == 2 + 3 + 2
    assert table[2].startswith("| 1 | 6,100 (6,000) | 40,000 | 20 s (21 s) |")  # with evaluation: 20 s + 2 x 0.5 s
    assert table[-2].startswith("| median | 5,900 | 40,000 | 20 s |")
    assert table[-1].startswith("| worst | 4,400 | not reached | not reached |")
    assert "2/3 seeds reached 5,000; 2/3 ended at or above the RL Zoo's 5,819" in seeds.verdict()


def test_the_spread_is_the_worst_time_over_the_median() -> None:
    runs = [run(seed, 6_000.0, [0.0] * (seed - 1) + [5_500.0], pace=pace) for seed, pace in ((1, 10), (2, 10), (3, 30))]
    assert Seeds.of("HalfCheetah-v5", runs).times_to == [10.0, 20.0, 90.0]
    assert Seeds.of("HalfCheetah-v5", runs).spread == 90.0 / 20.0


def test_over_more_seeds_than_five_it_reports_how_often_five_would_all_end_above_the_zoo() -> None:
    finals = [7_000.0, 6_500.0, 6_000.0, 5_900.0, 5_850.0, 5_000.0, 4_600.0]  # 5 of 7 at or above 5,819
    seeds = Seeds.of("HalfCheetah-v5", [run(seed, final, [final]) for seed, final in enumerate(finals, 1)])
    assert seeds.above_zoo == 5
    assert seeds.all_above_zoo_share == pytest.approx(1 / 21)  # one of the C(7, 5) = 21 ways to pick five
    verdict = seeds.verdict()
    assert "mean 5,836 ± 822 (sd across seeds)" in verdict
    assert "all 5 at or above 5,819 in 5% of the 21 ways to pick 5 of these 7 seeds" in verdict
    assert math.isnan(Seeds.of("HalfCheetah-v5", [run(1, 6_000.0, [6_000.0])]).all_above_zoo_share)


def bench(*arguments: str) -> subprocess.CompletedProcess:
    """launch/bench_learning.py run as a user runs it."""
    script = Path(__file__).resolve().parents[2] / "launch" / "bench_learning.py"
    return subprocess.run([sys.executable, str(script), *arguments], capture_output=True, text=True, timeout=120)


def test_reused_runs_pool_the_seeds_of_several_files_into_one_report(tmp_path: Path) -> None:
    def results(name: str, *seeds: int, ranks: int | None = None) -> Path:
        runs = [asdict(run(seed, 6_000.0 + seed, [5_500.0])) for seed in seeds]
        for entry in runs:
            if ranks is None:
                del entry["ranks"]  # a file from before --ranks
            else:
                entry["ranks"] = ranks
        path = tmp_path / name
        path.write_text(json.dumps({"machine_speed_cpu_s": 2.5, "results": {"HalfCheetah-v5": {"ftrain": runs}}}))
        return path

    first, second, out = results("a.json", 3, 1, ranks=1), results("b.json", 2), tmp_path / "out"
    done = bench("--envs", "halfcheetah", "--reuse", str(first), str(second), "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert "a cold 2-iteration smoke run" not in done.stdout  # nothing trains: this machine's speed is not theirs
    assert f"--reuse {first}: measured at machine speed 2.5 CPU-s" in done.stdout
    assert "HalfCheetah-v5, 3 seeds" in done.stdout and "3/3 seeds reached 5,000" in done.stdout
    report = json.loads((out / "results.json").read_text())
    pooled = report["results"]["HalfCheetah-v5"]["ftrain"]
    assert [(r["seed"], r["final_return"], r["ranks"]) for r in pooled] == [(1, 6_001, 1), (2, 6_002, 2), (3, 6_003, 1)]
    assert report["args"]["reuse"] == [str(first), str(second)] and (out / "halfcheetah.png").stat().st_size > 0
    assert " on " not in done.stdout  # one arithmetic (none recorded): no report apart
    with pytest.raises(SystemExit, match=r"seeds \[2\] of HalfCheetah-v5 are in more than one"):
        reused(
            "HalfCheetah-v5", {path: json.loads(path.read_text()) for path in (first, second, results("c.json", 2, 4))}
        )
    with pytest.raises(SystemExit, match=r"a.json: no runs of Hopper-v5 in it \(it has HalfCheetah-v5\)"):
        reused("Hopper-v5", {first: json.loads(first.read_text())})


@pytest.mark.parametrize(
    ("arguments", "message"),
    [(["--seeds", "1", "2", "1"], "--seeds 1 2 1: each seed once"), (["--ranks", "0"], "--ranks 0 --parallel 1: both")],
)
def test_bad_arguments_are_refused_in_one_line_before_anything_runs(
    tmp_path: Path, arguments: list[str], message: str
) -> None:
    done = bench("--envs", "hopper", *arguments, "--out", str(tmp_path))
    assert done.returncode == 2
    assert message in done.stderr and "Traceback" not in done.stderr
    assert list(tmp_path.iterdir()) == []  # refused before any run or smoke test


def test_seeds_of_several_arithmetics_are_also_reported_apart(tmp_path: Path) -> None:
    """A seed trains other bits on another CPU type: pooled runs of two are one report, and one per arithmetic."""
    amd, intel = "AMD EPYC, AVX512 kernels; torch 2.13.0+cpu", "Intel(R) Xeon(R), AVX512 kernels; torch 2.13.0+cpu"
    finals = {1: (amd, 6_500.0), 2: (intel, 5_500.0), 3: (amd, 6_100.0), 4: (intel, 5_900.0), 5: ("", 4_800.0)}
    runs = [run(seed, final, [final]) for seed, (_, final) in finals.items()]
    for entry, (kind, _) in zip(runs, finals.values(), strict=True):
        entry.arithmetic = kind
    path = tmp_path / "pooled.json"
    path.write_text(
        json.dumps({"machine_speed_cpu_s": 2.5, "results": {"HalfCheetah-v5": {"ftrain": [asdict(r) for r in runs]}}})
    )
    done = bench("--envs", "halfcheetah", "--reuse", str(path), "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr
    assert "HalfCheetah-v5: 4/5 seeds reached 5,000; 3/5 ended at or above" in done.stdout
    apart = [line for line in done.stdout.splitlines() if line.startswith("HalfCheetah-v5 on ")]
    assert apart == [
        "HalfCheetah-v5 on an arithmetic not recorded (seeds 5): " + Seeds.of("HalfCheetah-v5", runs[4:]).verdict(),
        f"HalfCheetah-v5 on {amd} (seeds 1, 3): " + Seeds.of("HalfCheetah-v5", runs[0:3:2]).verdict(),
        f"HalfCheetah-v5 on {intel} (seeds 2, 4): " + Seeds.of("HalfCheetah-v5", runs[1:4:2]).verdict(),
    ]
    assert "2/2 ended at or above the RL Zoo's 5,819" in apart[1] and "1/2 ended at or above" in apart[2]
