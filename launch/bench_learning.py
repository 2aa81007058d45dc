"""Learning benchmark: every seed of the shipped configs on HalfCheetah, Hopper, Walker2d and Ant (v5) as shipped,
with stable-baselines3 PPO (the RL Zoo's tuned hyperparameters) side by side on this machine if asked.

    .venv/bin/python launch/bench_learning.py [--envs halfcheetah hopper] [--seeds 1 2 3 4 5] [--steps 1000000]
        [--ranks 2] [--parallel 1] [--sb3-steps 0] [--out runs/bench_learning] [--reuse results.json ...]
        [--set key=value ...]

- ``configs/<env>.yaml`` trains for ``--steps`` steps at ``--ranks`` ranks (torchrun) once per seed, ``--parallel``
  seeds at a time (more than one: many seeds in less time, their times contended and not comparable). Its times are
  wall clock from launching torchrun, start-up and checkpoints included, with the clock stopped while the config's
  periodic evaluation (``eval.every``, 10 deterministic episodes) runs; the figures with it follow in parentheses.
  Its time and steps to the target are those of the first periodic evaluation at or above it; its return at the end
  is the final policy's mean over 10 deterministic episodes. Each run's storage (``metrics.csv``: losses, learning
  rate, action noise) stays under ``--out``/runs for a look at a seed that fell.
- Per environment it prints one row per seed, the median and the worst seed, how many seeds reached the target and
  the RL Zoo's return at the end, the mean and spread of the returns, and (over more than five seeds) how often five
  seeds drawn from them would all end at or above the Zoo's; it draws one curve per seed, their median and their band
  (``<env>.png``).
- SB3 PPO (``ftrain.tools.zoo``, ``--sb3-steps`` > 0) trains in a process of its own until a deterministic
  evaluation reaches the target, or for ``--sb3-steps`` steps; its time to 1M steps is scaled from that run.
- ``--reuse results.json ...`` takes ftrain's runs from earlier runs of this benchmark (to report again, to pool
  the seeds of several runs, or to measure SB3 only).
- Each run records its arithmetic (the CPU and libraries its ranks computed on, from its final manifest: a seed trains
  other bits on another, so its return is another draw); where the runs reported span more than one, each one's
  seeds are reported apart too.

Targets: 5,000 on HalfCheetah, the RL Zoo's return after 1M steps on the others. Writes ``results.json`` with every
curve, every seed's figures, the machine's load average around each run and its speed (``machine_speed.py``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import json
import math
import os
import shutil
import signal
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from machine_speed import cold_smoke  # noqa: E402

from ftrain.config import EnvConfig, for_world, load_config  # noqa: E402
from ftrain.errors import UserError  # noqa: E402
from ftrain.tools.zoo import ZOO, zoo_ppo  # noqa: E402
from ftrain.train.hooks import Hook  # noqa: E402

RANKS = 2
BENCHMARK_SEEDS = 5
"""Seeds of one benchmark run (``--seeds`` by default): over more seeds, how often that many all end well."""
EPISODES = 10
EVAL_SEED = 10_000
ENV_IDS = {"halfcheetah": "HalfCheetah-v5", "hopper": "Hopper-v5", "walker2d": "Walker2d-v5", "ant": "Ant-v5"}
TARGETS = {"HalfCheetah-v5": 5000.0}
"""The return every seed should reach, where it is not the Zoo's."""
WORKERS = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(Path(__file__).parent)}
"""Environment of the processes this benchmark launches: one OpenMP thread, this module importable."""


def target(env_id: str) -> float:
    return TARGETS.get(env_id, ZOO[env_id].zoo_return)


@dataclass
class Run:
    """One training run: its periodic evaluations and how long it took."""

    curve: list[tuple[float, ...]] = field(default_factory=list)
    """(environment steps, seconds since launch with the clock paused while evaluating, deterministic return) of
    each evaluation; ftrain's add the seconds it spent evaluating so far (0 in runs from before ``eval_time``,
    whose clock counted them)."""
    seconds: float = math.nan
    """Time to the end of the run, evaluation excluded (SB3: to 1M steps, scaled from its short run)."""
    eval_seconds: float = 0.0
    """Time ftrain spent in its periodic evaluation, on top of ``seconds``."""
    steps: int = 0
    final_return: float = math.nan
    episodes: list[float] = field(default_factory=list)
    """The returns of the final evaluation's episodes: a gait that falls over in some shows as a low one."""
    load: tuple[float, float] = (math.nan, math.nan)
    """The machine's 1-minute load average at the start and at the end."""
    seed: int = 0
    ranks: int = RANKS
    """ftrain's ranks (runs from before ``--ranks`` ran at 2)."""
    arithmetic: str = ""
    """What its ranks computed on, as its final manifest records it (``ftrain.ckpt.arithmetic``); "" for a run of
    an older benchmark, which did not record it."""

    @classmethod
    def from_json(cls, run: dict) -> Run:
        """An ftrain run from an earlier ``results.json``; its curve without evaluation times gets 0 for them."""
        return cls(**{**run, "curve": [(*point, 0.0)[:4] for point in run["curve"]]})

    def time_to(self, score: float, with_eval: bool = False) -> float:
        """Seconds to the first evaluation at or above ``score`` (``with_eval``: ftrain's evaluations counted)."""
        times = (point[1] + (point[3] if with_eval else 0.0) for point in self.curve if point[2] >= score)
        return next(times, math.nan)

    def steps_to(self, score: float) -> float:
        """Environment steps to the first evaluation at or above ``score``."""
        return next((point[0] for point in self.curve if point[2] >= score), math.nan)


class CurveHook(Hook):
    """Loaded into ftrain's workers by import path: after each periodic evaluation, rank 0 appends (environment
    steps, seconds since ``launched`` (epoch seconds) less the time spent evaluating, deterministic return, the
    time spent evaluating so far) to ``path`` as a JSON line."""

    def __init__(self, path: str, launched: float) -> None:
        self.path = Path(path)
        self.launched = launched
        self.evaluating = 0.0

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        score = metrics.get("eval_return", math.nan)
        if trainer.info.is_main and math.isfinite(score):
            self.evaluating += metrics["eval_time"]
            point = [metrics["env_steps"], time.time() - self.launched - self.evaluating, score, self.evaluating]
            with self.path.open("a") as file:
                file.write(json.dumps(point) + "\n")


def load_average() -> float:
    return float(Path("/proc/loadavg").read_text().split()[0])


def evaluate(act, env_config: EnvConfig, seed: int = EVAL_SEED) -> list[float]:
    """The returns of ``EPISODES`` deterministic episodes seeded ``seed``, ``seed + 1``, ..."""
    from ftrain.policy.robot import make_env  # torch and MuJoCo: not before the arguments are checked
    from ftrain.policy.rollout import rollout

    envs = [make_env(env_config) for _ in range(EPISODES)]
    try:
        return [episode.ret for episode in rollout(envs, act, EPISODES, seed)]
    finally:
        for env in envs:
            env.close()


def run_ftrain(
    name: str, seed: int, steps: int, overrides: list[str], work: Path, ranks: int = RANKS, stop_at: float = math.inf
) -> Run:
    """``configs/<name>.yaml`` for ``steps`` environment steps at ``ranks`` ranks, or until an evaluation returns
    ``stop_at`` or more (then stopped by SIGTERM, and the final policy not evaluated again)."""
    config_path = REPO / "configs" / f"{name}.yaml"
    config = for_world(load_config(str(config_path), overrides), ranks)
    per_iteration = config.env.in_all(ranks) * config.num_steps_per_env
    iterations = math.ceil(steps / per_iteration)
    digest = hashlib.sha256(" ".join(overrides).encode()).hexdigest()[:8]
    tag = f"{name}-{ranks}x{config.env.num_envs}-{digest}-seed{seed}"  # each case a storage and a curve of its own
    storage, curve = work / tag, work / f"{tag}.jsonl"
    shutil.rmtree(storage, ignore_errors=True)  # a fresh run, not a resume of an earlier one
    curve.unlink(missing_ok=True)
    run = Run(steps=iterations * per_iteration, load=(load_average(), math.nan), seed=seed, ranks=ranks)
    launched = time.time()
    hook = f"hooks=[{{target: 'bench_learning:CurveHook', kwargs: {{path: '{curve}', launched: {launched}}}}}]"
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}"]
    command = [*launcher, "-m", "ftrain", "train", str(config_path), "--storage", str(storage)]
    command += [f"iterations={iterations}", f"seed={seed}", "log.console=false", "log.tensorboard=false", hook]
    log = (work / f"{storage.name}.log").open("w+")
    proc = subprocess.Popen([*command, *overrides], cwd=REPO, env=WORKERS, stdout=log, stderr=subprocess.STDOUT)
    reached = False
    while proc.poll() is None:
        time.sleep(1)
        points = curve.read_text().splitlines() if curve.exists() else []
        if not reached and any(json.loads(point)[2] >= stop_at for point in points):
            reached = True
            proc.send_signal(signal.SIGTERM)  # torchrun passes it on: the workers save and exit
    wall, run.load = time.time() - launched, (run.load[0], load_average())
    if proc.returncode and not reached:
        log.seek(0)
        raise RuntimeError(f"ftrain failed on {name} seed {seed}:\n{log.read()[-3000:]}")
    run.curve = [tuple(json.loads(line)) for line in curve.read_text().splitlines()] if curve.exists() else []
    run.eval_seconds = run.curve[-1][3] if run.curve else 0.0
    run.seconds = wall - run.eval_seconds
    from ftrain.policy.load import load_policy  # torch: not before the arguments are checked

    if reached and not (storage / "checkpoints").is_dir():  # stopped at the target before its first commit
        return run
    policy = load_policy(str(storage))
    run.arithmetic = " | ".join(policy.manifest["arithmetic"])  # one line per arithmetic the ranks had: mostly one
    if not reached:
        run.episodes = evaluate(policy.act, policy.config.env, policy.config.eval.seed)
        run.final_return = statistics.fmean(run.episodes)
    return run


def run_sb3(env_id: str, steps: int, eval_every: int, work: Path) -> Run:
    out = work / f"sb3-{env_id}.json"
    run = Run(load=(load_average(), math.nan))
    launched = time.time()
    arguments = f"{env_id!r}, {steps}, {eval_every}, {launched}, {str(out)!r}"
    code = f"from bench_learning import sb3_worker; sb3_worker({arguments})"
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=WORKERS, capture_output=True, text=True)
    run.load = (run.load[0], load_average())
    if done.returncode:
        raise RuntimeError(f"SB3 failed on {env_id}:\n{done.stderr[-3000:]}")
    result = json.loads(out.read_text())
    (first_steps, first_seconds), (last_steps, last_seconds) = result["rollouts"][0], result["rollouts"][-1]
    rate = (last_steps - first_steps) / (last_seconds - first_seconds)
    run.seconds = first_seconds + (1_000_000 - first_steps) / rate
    run.curve = [tuple(point) for point in result["curve"]]
    run.steps, run.final_return = result["steps"], run.curve[-1][2] if run.curve else math.nan
    return run


def sb3_worker(env_id: str, steps: int, eval_every: int, launched: float, out: str) -> None:
    """In a process of its own: SB3 trains and evaluates until an evaluation reaches the target or ``steps`` steps;
    its clock (seconds since ``launched``) stops while it evaluates. Writes the evaluations and the clock at the end
    of each rollout to ``out``."""
    import torch
    from stable_baselines3.common.callbacks import BaseCallback

    paused = 0.0
    curve, rollouts = [], []

    def clock() -> float:
        return time.time() - launched - paused

    class Measure(BaseCallback):
        def _on_rollout_end(self) -> None:
            rollouts.append((self.num_timesteps, clock()))

        def _on_step(self) -> bool:
            nonlocal paused
            if self.num_timesteps % eval_every == 0:
                trained, started = clock(), time.time()
                venv = self.model.get_env()

                def act(obs: torch.Tensor) -> torch.Tensor:
                    return torch.as_tensor(self.model.predict(venv.normalize_obs(obs.numpy()), deterministic=True)[0])

                curve.append((self.num_timesteps, trained, statistics.fmean(evaluate(act, EnvConfig(env_id)))))
                paused += time.time() - started
                return curve[-1][2] < target(env_id)  # reached: its time to the target is known, stop
            return True

    model = zoo_ppo(env_id)
    model.learn(steps, callback=Measure())
    Path(out).write_text(json.dumps({"curve": curve, "rollouts": rollouts, "steps": model.num_timesteps}))


def plot(env_id: str, runs: list[Run], sb3: Run | None, path: Path, overrides: list[str]) -> None:
    """Return against environment steps (each seed, their median and band) and against wall time (each seed),
    SB3's run and the target; the title names the config's ``overrides``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for run in runs:
        for ax, column in zip(axes, (0, 1), strict=True):
            points = [(point[column], point[2]) for point in run.curve]
            ax.plot(*zip(*points, strict=True), "-", linewidth=1, label=f"seed {run.seed}")
    by_step = [{point[0]: point[2] for point in run.curve} for run in runs]
    steps = sorted(set.intersection(*(set(returns) for returns in by_step))) if runs else []
    at = [[returns[step] for returns in by_step] for step in steps]
    if len(runs) > 1 and steps:
        axes[0].fill_between(steps, [min(r) for r in at], [max(r) for r in at], color="tab:blue", alpha=0.12)
        median = [statistics.median(returns) for returns in at]
        axes[0].plot(steps, median, "-", color="black", linewidth=2, label=f"median of {len(runs)} seeds")
    for ax in axes if sb3 and sb3.curve else ():
        column = 0 if ax is axes[0] else 1
        points = [(point[column], point[2]) for point in sb3.curve]
        ax.plot(*zip(*points, strict=True), "o-", color="tab:gray", markersize=3, label="SB3 PPO, RL Zoo")
    for ax, label in zip(axes, ("environment steps", "wall time (s), evaluation excluded"), strict=True):
        ax.axhline(target(env_id), color="gray", linestyle="--", linewidth=1, label=f"target {target(env_id):,.0f}")
        ax.set_xlabel(label)
        ax.set_ylabel("deterministic return (10 episodes)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize="x-small")
    config = "shipped config" + (f" with {' '.join(overrides)}" if overrides else "")
    ranks = " or ".join(str(n) for n in sorted({run.ranks for run in runs}))
    figure.suptitle(f"{env_id}: ftrain at {ranks} rank{'' if ranks == '1' else 's'}, {config}")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=72)
    plt.close(figure)


def _seconds(value: float) -> str:
    return _reached(value, " s")


def _reached(value: float, unit: str = "") -> str:
    """A time or step count, or "not reached" where there is none."""
    return f"{value:,.0f}{unit}" if math.isfinite(value) else "not reached"


@dataclass
class Seeds:
    """What the seeds of one environment reached: the median and the worst seed of each figure (the worst time or
    step count of a seed that did not reach the target is infinite)."""

    target: float
    zoo: float
    returns: list[float]
    steps_to: list[float]
    times_to: list[float]

    @classmethod
    def of(cls, env_id: str, runs: list[Run]) -> Seeds:
        goal, zoo = target(env_id), float(ZOO[env_id].zoo_return)
        returns = [run.final_return for run in runs]
        steps_to = [or_inf(run.steps_to(goal)) for run in runs]
        times_to = [or_inf(run.time_to(goal)) for run in runs]
        return cls(goal, zoo, returns, steps_to, times_to)

    @property
    def reached(self) -> int:
        return sum(math.isfinite(steps) for steps in self.steps_to)

    @property
    def above_zoo(self) -> int:
        return sum(value >= self.zoo for value in self.returns)

    @property
    def worst_return(self) -> float:
        return min(self.returns)

    @property
    def all_above_zoo_share(self) -> float:
        """The share of the ways to pick ``BENCHMARK_SEEDS`` of these seeds in which every one ends at or above the
        Zoo's: how often a benchmark of that many seeds would find its worst seed there (NaN for fewer seeds)."""
        n = len(self.returns)
        return (
            math.comb(self.above_zoo, BENCHMARK_SEEDS) / math.comb(n, BENCHMARK_SEEDS)
            if n >= BENCHMARK_SEEDS
            else math.nan
        )

    @property
    def spread(self) -> float:
        """The worst seed's time to the target over the median's (infinite if a seed did not reach it)."""
        return max(self.times_to) / statistics.median(self.times_to)

    def verdict(self) -> str:
        n = len(self.returns)
        spread = f" ± {statistics.stdev(self.returns):,.0f} (sd across seeds)" if n > 1 else ""
        verdict = (
            f"{self.reached}/{n} seeds reached {self.target:,.0f}; {self.above_zoo}/{n} ended at or above the RL Zoo's "
            f"{self.zoo:,.0f}; worst at the end {self.worst_return:,.0f}, median {statistics.median(self.returns):,.0f}"
            f", mean {statistics.fmean(self.returns):,.0f}{spread}; worst time to {self.target:,.0f} / median: "
            f"{self.spread:.2f}"
        )
        if n > BENCHMARK_SEEDS:
            verdict += (
                f"; all {BENCHMARK_SEEDS} at or above {self.zoo:,.0f} in {self.all_above_zoo_share:.0%} of the "
                f"{math.comb(n, BENCHMARK_SEEDS):,} ways to pick {BENCHMARK_SEEDS} of these {n} seeds"
            )
        return verdict


def by_arithmetic(env_id: str, runs: list[Run]) -> list[str]:
    """Where ``runs`` computed on more than one arithmetic, each one's seeds and verdict, apart (none where one)."""
    kinds = sorted({run.arithmetic for run in runs})
    if len(kinds) < 2:
        return []
    lines = []
    for kind in kinds:
        own = [run for run in runs if run.arithmetic == kind]
        seeds = ", ".join(str(run.seed) for run in own)
        lines.append(f"on {kind or 'an arithmetic not recorded'} (seeds {seeds}): {Seeds.of(env_id, own).verdict()}")
    return lines


def or_inf(value: float) -> float:
    """A time or step count never reached (NaN) as infinite: the worst of any."""
    return value if math.isfinite(value) else math.inf


def seed_table(env_id: str, runs: list[Run]) -> str:
    """One row per seed, then the median and the worst seed."""
    seeds, goal = Seeds.of(env_id, runs), f"{target(env_id):,.0f}"
    lines = [
        f"| seed | return at the end (its worst episode) | steps to {goal} | time to {goal} (with evaluation) "
        "| time to the end (with evaluation) | load average at start, end |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for run in runs:
        with_eval = run.time_to(target(env_id), with_eval=True)
        lines.append(
            f"| {run.seed} | {run.final_return:,.0f}{f' ({min(run.episodes):,.0f})' if run.episodes else ''} "
            f"| {_reached(run.steps_to(target(env_id)))} "
            f"| {_seconds(run.time_to(target(env_id)))} ({_seconds(with_eval)}) "
            f"| {run.seconds:,.0f} s ({run.seconds + run.eval_seconds:,.0f} s) | {run.load[0]:.1f}, {run.load[1]:.1f} |"
        )
    ends = [run.seconds for run in runs]
    median = [statistics.median(figures) for figures in (seeds.returns, seeds.steps_to, seeds.times_to, ends)]
    worst = [seeds.worst_return, max(seeds.steps_to), max(seeds.times_to), max(ends)]
    for name, (returns, steps, times, end) in (("median", median), ("worst", worst)):
        lines.append(f"| {name} | {returns:,.0f} | {_reached(steps)} | {_seconds(times)} | {end:,.0f} s | |")
    return "\n".join(lines)


HEADER = (
    "| environment | ftrain return at the end: median (range) | RL Zoo | ftrain time to the end (with evaluation) "
    "| ftrain time to target (with evaluation) | SB3 time to 1M steps | SB3 time to target "
    "| ftrain / SB3: to the end, to target (with ftrain's evaluation) |\n"
    "| --- | --- | --- | --- | --- | --- | --- | --- |"
)


def against_sb3(env_id: str, runs: list[Run], sb3: Run) -> str:
    """One row of the comparison with SB3 (ftrain's times are medians over the seeds; a target counts if most seeds
    reached it). ftrain's times leave its periodic evaluation out, as SB3's do; the figures with it follow in
    parentheses."""
    goal = target(env_id)
    returns = [run.final_return for run in runs]
    reached = [run.time_to(goal) for run in runs if math.isfinite(run.time_to(goal))]
    total = statistics.median(run.seconds for run in runs)
    total_with_eval = statistics.median(run.seconds + run.eval_seconds for run in runs)
    to_goal, to_goal_with_eval = (
        statistics.median(run.time_to(goal, with_eval) for run in runs) if len(reached) * 2 > len(runs) else math.nan
        for with_eval in (False, True)
    )
    sb3_goal = sb3.time_to(goal)
    reached_by_sb3 = math.isfinite(sb3_goal)
    bound = sb3_goal if reached_by_sb3 else sb3.curve[-1][1]  # not reached: it takes longer than its whole run
    cells = [
        env_id,
        f"{statistics.median(returns):,.0f} ({min(returns):,.0f} to {max(returns):,.0f})",
        f"{ZOO[env_id].zoo_return:,}",
        f"{total:,.0f} s ({total_with_eval:,.0f} s; {runs[0].steps:,} steps)",
        f"{_seconds(to_goal)} ({_seconds(to_goal_with_eval)}; {len(reached)}/{len(runs)} reached {goal:,.0f})",
        f"{sb3.seconds:,.0f} s (scaled from {sb3.steps:,} steps)",
        _seconds(sb3_goal) if reached_by_sb3 else f"> {bound:,.0f} s (not in {sb3.steps:,} steps)",
        f"{total / sb3.seconds:.2f}, {'' if reached_by_sb3 else '< '}{to_goal / bound:.2f} "
        f"({total_with_eval / sb3.seconds:.2f}, {'' if reached_by_sb3 else '< '}{to_goal_with_eval / bound:.2f})",
    ]
    return "| " + " | ".join(cells) + " |"


def train_seeds(name: str, args: argparse.Namespace, work: Path) -> list[Run]:
    """Every seed of ``args.seeds`` on ``configs/<name>.yaml``, ``args.parallel`` at a time, in the order of the seeds;
    each printed as it ends."""
    env_id = ENV_IDS[name]

    def train(seed: int) -> Run:
        run = run_ftrain(name, seed, int(args.steps), args.set, work, ranks=args.ranks)
        print(
            f"{env_id} seed {seed}: return {run.final_return:,.1f} after {run.steps:,} steps in "
            f"{run.seconds:,.0f} s + {run.eval_seconds:,.0f} s evaluating, "
            f"target {target(env_id):,.0f} at {_seconds(run.time_to(target(env_id)))}, load {run.load}",
            flush=True,
        )
        return run

    with concurrent.futures.ThreadPoolExecutor(max_workers=args.parallel) as pool:
        return list(pool.map(train, args.seeds))


def reused(env_id: str, files: dict[Path, dict]) -> list[Run]:
    """The runs of ``env_id`` in earlier ``results.json`` files (read, by path), pooled; a file without them, or a seed
    found twice, is an error."""
    runs = []
    for path, report in files.items():
        earlier = report["results"]
        if env_id not in earlier:
            sys.exit(f"--reuse {path}: no runs of {env_id} in it (it has {', '.join(earlier)}); pick them with --envs")
        runs += [Run.from_json(run) for run in earlier[env_id]["ftrain"]]
    seeds = [run.seed for run in runs]
    if len(set(seeds)) < len(seeds):
        twice = sorted({seed for seed in seeds if seeds.count(seed) > 1})
        sys.exit(f"--reuse: seeds {twice} of {env_id} are in more than one of the files; pool each seed once")
    return sorted(runs, key=lambda run: run.seed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=list(ENV_IDS), choices=list(ENV_IDS))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(range(1, BENCHMARK_SEEDS + 1)))
    parser.add_argument("--steps", type=float, default=1e6, help="environment steps of each ftrain run")
    parser.add_argument("--ranks", type=int, default=RANKS, help="ranks of each ftrain run")
    parser.add_argument(
        "--parallel", type=int, default=1, help="ftrain runs at a time (more than 1: their times are contended)"
    )
    parser.add_argument(
        "--sb3-steps", type=float, default=0, help="SB3 runs until the target or this many steps (0: no SB3)"
    )
    parser.add_argument(
        "--reuse",
        type=Path,
        nargs="+",
        help="take ftrain's runs from these earlier results.json files (their seeds pooled) instead of training again",
    )
    parser.add_argument("--sb3-eval-every", type=float, default=10_000)
    parser.add_argument("--out", type=Path, default=REPO / "runs" / "bench_learning")
    parser.add_argument("--set", nargs="*", default=[], metavar="key=value", help="config overrides for ftrain")
    args = parser.parse_args()
    if len(set(args.seeds)) < len(args.seeds):
        parser.error(f"--seeds {' '.join(map(str, args.seeds))}: each seed once (a seed's runs share one storage)")
    if args.ranks < 1 or args.parallel < 1:
        parser.error(f"--ranks {args.ranks} --parallel {args.parallel}: both at least 1")
    for name in args.envs:  # each config as these ranks run it, before any run: a count they cannot share is refused
        try:
            for_world(load_config(str(REPO / "configs" / f"{name}.yaml"), args.set), args.ranks)
        except UserError as error:
            parser.error(f"--envs {name} --ranks {args.ranks}: {error}")
    if args.parallel > 1:
        print(f"--parallel {args.parallel}: runs share the machine; compare their returns and steps, not their times")
    work = args.out / "runs"
    work.mkdir(parents=True, exist_ok=True)
    speed = None  # of this machine now: nothing to measure where every run is reused (each file has its own)
    if args.sb3_steps or not args.reuse:
        speed = cold_smoke()[0]
        print(
            f"machine speed: a cold 2-iteration smoke run took {speed:.1f} CPU-s (launch/machine_speed.py)", flush=True
        )
    files = {path: json.loads(path.read_text()) for path in args.reuse or []}
    for path, report in files.items():
        print(f"--reuse {path}: measured at machine speed {report['machine_speed_cpu_s']} CPU-s")
    results, tables, rows = {}, [], []
    for name in args.envs:
        env_id = ENV_IDS[name]
        sb3 = None
        if args.sb3_steps:
            sb3 = run_sb3(env_id, int(args.sb3_steps), int(args.sb3_eval_every), work)
            print(f"{env_id} SB3: {sb3.seconds:,.0f} s to 1M steps (scaled), load {sb3.load}", flush=True)
        runs = reused(env_id, files) if files else train_seeds(name, args, work)
        plot(env_id, runs, sb3, args.out / f"{name}.png", args.set)
        seeds = Seeds.of(env_id, runs)
        results[env_id] = {"ftrain": [asdict(run) for run in runs], "sb3": asdict(sb3) if sb3 else None}
        counts = {"reached": seeds.reached, "above_zoo": seeds.above_zoo, "verdict": seeds.verdict()}
        results[env_id]["seeds"] = asdict(seeds) | counts
        tables.append(f"{env_id}, {len(runs)} seeds, {runs[0].steps:,} steps each:\n{seed_table(env_id, runs)}")
        tables[-1] += f"\n{env_id}: {seeds.verdict()}"
        tables[-1] += "".join(f"\n{env_id} {line}" for line in by_arithmetic(env_id, runs))
        rows += [against_sb3(env_id, runs, sb3)] if sb3 else []
    settings = json.loads(json.dumps(vars(args), default=str))  # paths as strings
    summary = {"args": settings, "machine_speed_cpu_s": speed, "results": results}
    (args.out / "results.json").write_text(json.dumps(summary, indent=1))
    print("\n\n".join(tables))
    if rows:
        print(f"\n{HEADER}\n" + "\n".join(rows))


if __name__ == "__main__":
    main()
