"""Strong scaling: the same learning, sooner. HalfCheetah-v5 trained to an evaluation return of ``--target`` at each
rank count of ``--ranks``, with one global batch that the ranks split, against what the machine allows.

    .venv/bin/python launch/bench_time_to_target.py [--ranks 1 2] [--seeds 1 2 3] [--target 5000] [--steps 3e6]

The shipped ``configs/halfcheetah.yaml`` is tuned at 2 ranks x 16 environments: 512 environment steps per iteration,
4 minibatches of 128 samples in all. At N ranks each rank steps ``--global-envs`` / N environments, so every
iteration collects the same 512 steps and every minibatch update averages the gradients of the same 128 samples
over the ranks; the learning-rate schedule, in iterations, is the same. Only the environments' seeds and the order of
the sums differ, so the curves against environment steps should agree, and the time to the target should fall with N.

Each run stops at its first periodic evaluation (10 deterministic episodes, every ``eval.every`` iterations) at or
above the target; its time is wall clock from launching torchrun, start-up included, with the clock paused while it
evaluates (``bench_learning.CurveHook``). A run that does not reach it by ``--steps`` steps counts as not reached.

What the machine allows: the iteration rate of one rank stepping all ``--global-envs`` environments alone, against
N x that of the slowest of N independent 1-rank runs of ``--global-envs`` / N environments started side by side
(``ftrain.tools.bench.run_side_by_side``, median iterations). Their ratio is the speed-up N ranks could give at best
on these cores; the table shows the speed-up of the time to the target against it. Writes a plot of return against
wall time (one colour per rank count, a line per seed) and ``results.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
from dataclasses import asdict
from pathlib import Path

import bench_learning
from bench_learning import Run, run_ftrain

from ftrain.tools.bench import run_side_by_side

COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")


def allowed_speedups(ranks: list[int], global_envs: int, iterations: int) -> dict[int, float]:
    """For each N: N x the steps/s of the slowest of N side-by-side 1-rank runs of ``global_envs`` / N environments,
    over the steps/s of one rank stepping all of them alone."""
    alone = run_side_by_side(iterations, [1], overrides=(f"env.num_envs={global_envs}",))[0]["median_steps_per_s"]
    speedups = {}
    for count in ranks:
        beside = run_side_by_side(iterations, [1] * count, overrides=(f"env.num_envs={global_envs // count}",))
        speedups[count] = count * min(run["median_steps_per_s"] for run in beside) / alone
        print(f"  N={count}: at best {speedups[count]:.2f}x one rank ({alone:,.0f} steps/s alone)", flush=True)
    return speedups


def plot(runs: dict[int, list[Run]], target: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, column, label in ((axes[0], 0, "environment steps"), (axes[1], 1, "wall time (s), evaluation excluded")):
        for color, (count, seeds) in zip(COLORS, runs.items(), strict=False):
            for index, run in enumerate(seeds):
                points = [(point[column], point[2]) for point in run.curve]
                name = f"{count} rank{'s' if count > 1 else ''} ({len(seeds)} seeds)" if index == 0 else None
                ax.plot(*zip(*points, strict=True), "-", color=color, linewidth=1, label=name)
        ax.axhline(target, color="gray", linestyle="--", linewidth=1, label=f"target {target:,.0f}")
        ax.set_xlabel(label)
        ax.set_ylabel("deterministic return (10 episodes)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize="small")
    figure.suptitle("HalfCheetah-v5, one global batch of 512 steps split across the ranks")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=72)
    plt.close(figure)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ranks", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--target", type=float, default=5000.0)
    parser.add_argument("--steps", type=float, default=3e6, help="environment steps at most per run")
    parser.add_argument("--global-envs", type=int, default=32, help="environments in all, split across the ranks")
    parser.add_argument("--iterations", type=int, default=40, help="timed iterations of each throughput run")
    parser.add_argument("--out", type=Path, default=bench_learning.REPO / "runs" / "bench_time_to_target")
    args = parser.parse_args()
    if any(args.global_envs % count for count in args.ranks):
        parser.error(f"--global-envs {args.global_envs} must divide by every rank count of --ranks {args.ranks}")
    runs: dict[int, list[Run]] = {count: [] for count in args.ranks}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:  # seed by seed, every rank count: a drift of the machine hits them alike
            for count in args.ranks:
                overrides = [f"env.num_envs={args.global_envs // count}"]
                run = run_ftrain("halfcheetah", seed, int(args.steps), overrides, Path(tmp), count, args.target)
                runs[count].append(run)
                reached = run.time_to(args.target)
                where = next((point[0] for point in run.curve if point[2] >= args.target), math.nan)
                print(
                    f"seed {seed}, {count} rank(s): {args.target:,.0f} at {reached:,.0f} s, {where:,.0f} steps "
                    f"(+{run.eval_seconds:,.0f} s evaluating), load {run.load}",
                    flush=True,
                )
    print("what the machine allows (throughput runs, the same cores, right after):", flush=True)
    allowed = allowed_speedups(args.ranks, args.global_envs, args.iterations)
    times = {count: [run.time_to(args.target) for run in seeds] for count, seeds in runs.items()}
    base = statistics.median(times[args.ranks[0]])
    columns = f"time to {args.target:,.0f}: median (range) | seeds reached | steps to it: median"
    print(f"\n| ranks x envs | {columns} | speed-up vs {args.ranks[0]} rank(s) | at best (ceiling) | fraction of it |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for count, seeds in runs.items():
        reached = [time for time in times[count] if math.isfinite(time)]
        steps = [next((p[0] for p in run.curve if p[2] >= args.target), math.nan) for run in seeds]
        middle = statistics.median(times[count])
        speedup = base / middle
        relative = allowed[count] / allowed[args.ranks[0]]
        spread = f"{min(times[count]):,.0f} to {max(times[count]):,.0f}"
        print(
            f"| {count} x {args.global_envs // count} | {middle:,.0f} s ({spread}) | {len(reached)}/{len(seeds)} "
            f"| {statistics.median(steps):,.0f} | {speedup:.2f} | {relative:.2f} | {speedup / relative:.2f} |"
        )
    plot(runs, args.target, args.out / "halfcheetah.png")
    results = {str(count): [asdict(run) for run in seeds] for count, seeds in runs.items()}
    (args.out / "results.json").write_text(json.dumps({"args": vars(args) | {"out": str(args.out)}, "runs": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
