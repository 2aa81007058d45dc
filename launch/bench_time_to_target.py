"""Strong scaling: the same learning, sooner. HalfCheetah-v5 trained to an evaluation return of ``--target`` in each
case of ``--cases`` (ranks x environments per rank), against what the machine allows.

    .venv/bin/python launch/bench_time_to_target.py [--cases 1x32 2x16 2x16:dp] [--seeds 1 2 3] [--target 5000]
        [--config halfcheetah] [--set KEY=VALUE ...]

The shipped ``configs/halfcheetah.yaml`` shares 32 environments among the ranks: 512 environment steps per iteration,
10 epochs of 4 minibatches. The cases (default: the config's global batch at 1 rank, and at 2 ranks split and
data-parallel: ``1x32 2x16 2x16:dp``) keep that global batch, so the learning per environment step is the same, and
only the time it takes can differ:

- ``2x16``: two ranks split the update (``split_update``, the default at two ranks): rank 0 learns the actor and
  rank 1 the critic, each on the whole batch; they meet to gather the rollout and to exchange the models, not at
  every minibatch. The update is one rank's update of that batch, bit for bit.
- ``2x16:dp``: data-parallel (``split_update=false``): every rank makes all 40 minibatch updates of both models on
  its half of each minibatch (their cost hardly shrinks with the samples), and every one is a meeting of the ranks.
- Other cases (e.g. ``2x32``, a doubled batch) change the learning; their learning-rate schedule is scaled to end at
  the same number of environment steps (``algorithm.schedule_iterations``). ``2x32/8``: a doubled batch in 8
  minibatches, so that a minibatch holds as many samples as the config's, and each sample makes as many gradient
  steps: the large-batch way to use more ranks, each rank doing a whole 1-rank job's rollout.

Each run stops at its first periodic evaluation (10 deterministic episodes, every ``eval.every`` iterations) at or
above the target; its time is wall clock from launching torchrun, start-up included, with the clock paused while it
evaluates (``bench_learning.CurveHook``). A run that does not reach it by ``--steps`` steps counts as not reached.
Seeds go round the cases, so a drift of the machine hits every case alike.

What the machine allows each case: N x the steps/s of the slowest of N independent 1-rank runs started side by side
(``ftrain.tools.bench.run_side_by_side``, median iterations), each doing what one rank of the case does alone (its
environments; for a split update, the whole job of both ranks' environments, which the two ranks share), against the
first case's (a 1-rank case's: one run alone). For a case with the first case's learning per environment step, it bounds
the speed-up of the time to the target too. Beside it, the steps/s each case reached (from a run's first evaluation to
the one at the target: start-up left out). Writes a plot of return against environment steps and wall time (a colour per
case, a line per seed) and ``results.json`` to ``--out``.
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
from typing import NamedTuple

import bench_learning
from bench_learning import Run, or_inf, run_ftrain

from ftrain.config import load_config
from ftrain.tools.bench import run_side_by_side

COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple")
OWN_KEYS = (
    "iterations",
    "seed",
    "hooks",
    "log",
    "checkpoint.",
    "env.num_envs",
    "env.total_envs",
    "algorithm.num_mini_batches",
    "algorithm.schedule_iterations",
)
"""What ``--set`` may not override: the benchmark's own settings of a case, a seed and a timed run."""


class Case(NamedTuple):
    """``RANKSxENVS`` (environments per rank), ``/MINIBATCHES`` for another number of minibatches than the config's,
    ``:dp`` for a data-parallel update where two ranks would split it."""

    ranks: int
    envs: int
    data_parallel: bool
    mini_batches: int | None = None

    @property
    def split(self) -> bool:
        return self.ranks == 2 and not self.data_parallel

    def overrides(self, envs: int | None = None) -> list[str]:
        """What one run of the case changes of the config (``envs``: per rank, if not the case's)."""
        overrides = [f"env.num_envs={envs or self.envs}"]
        overrides += [f"algorithm.num_mini_batches={self.mini_batches}"] if self.mini_batches else []
        return overrides + (["split_update=false"] if self.data_parallel else [])

    def __str__(self) -> str:
        mini_batches = f"/{self.mini_batches}" if self.mini_batches else ""
        return f"{self.ranks}x{self.envs}{mini_batches}{':dp' if self.data_parallel else ''}"


def parse_case(case: str) -> Case:
    shape, _, mode = case.partition(":")
    shape, _, mini_batches = shape.partition("/")
    ranks, _, envs = shape.partition("x")
    numbers = (ranks, envs, *([mini_batches] if mini_batches else []))
    if not all(number.isdigit() and int(number) for number in numbers) or mode not in ("", "dp"):
        raise argparse.ArgumentTypeError(f"{case!r} is not RANKSxENVS[/MINIBATCHES][:dp], e.g. 2x16 or 2x32/8")
    return Case(int(ranks), int(envs), mode == "dp", int(mini_batches) if mini_batches else None)


def best_speed(case: Case, iterations: int, config: Path, extra: tuple[str, ...]) -> float:
    """The steps/s the machine gives ``case`` at best: N x the steps/s of the slowest of N side-by-side 1-rank runs
    of what each rank would do alone (one run alone for a 1-rank case). A split update shares one job of all the
    environments between its two ranks, so its bound is two such whole jobs side by side. ``extra``: overrides of
    every run (no evaluation in a throughput run, whatever they say)."""
    envs = case.envs * case.ranks if case.split else case.envs
    overrides = (*case.overrides(envs), *extra, "eval.every=0")
    beside = run_side_by_side(iterations, [1] * case.ranks, overrides=overrides, config=config)
    return case.ranks * min(run["median_steps_per_s"] for run in beside)


def describe(case: Case) -> str:
    update = ", split update" if case.split else ", data-parallel" if case.ranks > 1 else ""
    return f"{case.ranks} rank{'s' if case.ranks > 1 else ''} x {case.envs} envs{update}"


def rate(run: Run, target: float) -> float:
    """Environment steps per second from a run's first evaluation to the first at or above ``target`` (start-up and
    evaluation left out)."""
    first = run.curve[0] if run.curve else None
    hit = next((point for point in run.curve if point[2] >= target), None)
    if first is None or hit is None or hit is first:
        return math.nan
    return (hit[0] - first[0]) / (hit[1] - first[1])


def plot(runs: dict[str, list[Run]], target: float, env_id: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, column, label in ((axes[0], 0, "environment steps"), (axes[1], 1, "wall time (s), evaluation excluded")):
        for color, (case, seeds) in zip(COLORS, runs.items(), strict=False):
            for index, run in enumerate(seeds):
                points = [(point[column], point[2]) for point in run.curve]
                name = describe(parse_case(case)) if index == 0 else None
                ax.plot(*zip(*points, strict=True), "-", color=color, linewidth=1, label=name)
        ax.axhline(target, color="gray", linestyle="--", linewidth=1, label=f"target {target:,.0f}")
        ax.set_xlabel(label)
        ax.set_ylabel("deterministic return (10 episodes)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize="small")
    figure.suptitle(f"{env_id} to an evaluation return of {target:,.0f}: ranks x environments per rank")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=72)
    plt.close(figure)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    shapes = "RANKSxENVS[/MINIBATCHES][:dp] (default: the config's batch at 1 rank, 2 split, 2 data-parallel)"
    parser.add_argument("--cases", type=parse_case, nargs="+", default=None, help=shapes)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--target", type=float, default=5000.0)
    parser.add_argument("--steps", type=float, default=3e6, help="environment steps at most per run")
    horizon = "environment steps at which the learning rate reaches zero (default: the config's own horizon)"
    parser.add_argument("--schedule-steps", type=float, default=None, help=horizon)
    parser.add_argument("--iterations", type=int, default=30, help="timed iterations of each throughput run")
    parser.add_argument("--out", type=Path, default=bench_learning.REPO / "runs" / "bench_time_to_target")
    parser.add_argument("--config", default="halfcheetah", help="the config of configs/, by name")
    every = "config overrides of every run of every case, e.g. algorithm.learning_rate=3e-4 eval.every=10"
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help=every)
    args = parser.parse_args()
    config_path = bench_learning.REPO / "configs" / f"{args.config}.yaml"
    if not config_path.exists():
        parser.error(f"--config {args.config}: no {config_path.relative_to(bench_learning.REPO)}")
    for item in args.set:
        if item.partition("=")[0].startswith(OWN_KEYS):
            parser.error(f"--set {item}: the benchmark sets {item.partition('=')[0]} itself (cases, seeds, runs)")
    config = load_config(str(config_path))
    tuned = config.env.in_all(2)  # the config's global batch, in environments (per-rank counts: tuned at 2 ranks)
    cases = args.cases or [Case(1, tuned, False), Case(2, tuned // 2, False), Case(2, tuned // 2, True)]
    names = [str(case) for case in cases]
    horizon = args.schedule_steps or config.algorithm.schedule_iterations * tuned * config.num_steps_per_env
    runs: dict[str, list[Run]] = {name: [] for name in names}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for name, case in zip(names, cases, strict=True):
                schedule = round(horizon / (case.ranks * case.envs * config.num_steps_per_env))
                overrides = [*case.overrides(), f"algorithm.schedule_iterations={schedule}", *args.set]
                run = run_ftrain(args.config, seed, int(args.steps), overrides, Path(tmp), case.ranks, args.target)
                runs[name].append(run)
                where = run.steps_to(args.target)
                print(
                    f"seed {seed}, {name}: {args.target:,.0f} at {run.time_to(args.target):,.0f} s, {where:,.0f} steps "
                    f"(+{run.eval_seconds:,.0f} s evaluating), load {run.load}",
                    flush=True,
                )
    print("what the machine allows (throughput runs, the same cores, right after):", flush=True)
    best = [best_speed(case, args.iterations, config_path, tuple(args.set)) for case in cases]
    allowed = {name: speed / best[0] for name, speed in zip(names, best, strict=True)}
    print(f"\n| ranks x envs | time to {args.target:,.0f}: median (range) | worst seed: its time / the median ", end="")
    print(f"| seeds | steps to it: median | speed-up vs {names[0]} | steps/s at best (ceiling) ", end="")
    print("| steps/s reached: median (range) |")
    print("| --- " * 8 + "|")
    times = {name: [run.time_to(args.target) for run in seeds] for name, seeds in runs.items()}
    rates = {name: [rate(run, args.target) for run in seeds] for name, seeds in runs.items()}
    for name, seeds in runs.items():
        reached = [time for time in times[name] if math.isfinite(time)]
        steps = [run.steps_to(args.target) for run in seeds]
        middle, spread = statistics.median(times[name]), f"{min(times[name]):,.0f} to {max(times[name]):,.0f}"
        worst = max(seeds, key=lambda run: or_inf(run.time_to(args.target)))
        worst_time = or_inf(worst.time_to(args.target))
        speed, speeds = statistics.median(rates[name]), f"{min(rates[name]):,.0f} to {max(rates[name]):,.0f}"
        print(
            f"| {name} | {middle:,.0f} s ({spread}) | seed {worst.seed}: {worst_time / middle:.2f} "
            f"| {len(reached)}/{len(seeds)} reached "
            f"| {statistics.median(steps):,.0f} | {statistics.median(times[names[0]]) / middle:.2f} "
            f"| {allowed[name]:.2f} | {speed / statistics.median(rates[names[0]]):.2f}: {speed:,.0f} ({speeds}) |"
        )
    plot(runs, args.target, config.env.id, args.out / f"{args.config}.png")
    results = {name: [asdict(run) for run in seeds] for name, seeds in runs.items()}
    settings = vars(args) | {"out": str(args.out), "cases": names}
    (args.out / "results.json").write_text(json.dumps({"args": settings, "runs": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
