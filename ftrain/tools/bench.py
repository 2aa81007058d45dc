"""``ftrain bench``: PPO throughput on HalfCheetah-v5, ftrain against its peers, measured side by side in one run.

Every case runs in its own process with one torch thread (the 2-rank case: two processes), with the same work per
iteration, in two settings: ``fixed`` (16 envs x 24 steps per rank, 5 epochs x 4 minibatches, a 64x64 ELU MLP: the
setting of the first measurements) and ``config`` (the work of the shipped ``configs/halfcheetah.yaml``: its rollout
length, epochs, minibatches and network). Each case reports steady-state environment steps per second over the timed
iterations, after warm-up iterations that are not counted (periodic evaluation off):

- ``raw``: gymnasium's vector env stepped with random actions, no learning: the limit;
- ``rsl_rl``: rsl-rl's own OnPolicyRunner, one process;
- ``sb3``: stable-baselines3 PPO with the same settings, one process (the ``bench`` extra);
- ``ftrain-1``, ``ftrain-2``: ``ftrain train`` with 1 and 2 ranks (torchrun), no checkpoints in the timed window.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from ftrain.config import load_config
from ftrain.errors import UserError
from ftrain.files import replace_text
from ftrain.progress import Progress
from ftrain.train.hooks import Hook

ENV_ID = "HalfCheetah-v5"
NUM_ENVS = 16
WARMUP = 3
CONFIG = Path(__file__).resolve().parents[2] / "configs" / "halfcheetah.yaml"


@dataclass(frozen=True)
class Setting:
    """The work of one PPO iteration (per rank: ``NUM_ENVS`` environments), which every case of a setting does."""

    steps: int
    epochs: int
    minibatches: int
    hidden: tuple[int, ...]
    activation: str

    def overrides(self) -> list[str]:
        """ftrain config overrides for this work (the rest of the shipped config, e.g. normalisation, stays)."""
        hidden = ",".join(map(str, self.hidden))
        return [
            f"env.num_envs={NUM_ENVS}",
            f"num_steps_per_env={self.steps}",
            f"algorithm.num_learning_epochs={self.epochs}",
            f"algorithm.num_mini_batches={self.minibatches}",
            f"policy.hidden_dims=[{hidden}]",
            f"policy.activation={self.activation}",
        ]


def shipped_setting() -> Setting:
    config = load_config(str(CONFIG))
    a, policy = config.algorithm, config.policy
    hidden = tuple(policy.hidden_dims)
    return Setting(config.num_steps_per_env, a.num_learning_epochs, a.num_mini_batches, hidden, policy.activation)


SETTINGS = {"fixed": lambda: Setting(24, 5, 4, (64, 64), "elu"), "config": shipped_setting}


class ThroughputHook(Hook):
    """Rank 0 writes, to ``path`` as JSON: the steady-state global steps/s (iterations after the warm-up), the same
    from the median iteration time (robust to the bursts of other work that these machines see), the mean
    milliseconds of each phase (``ftrain.train.phases``) over the timed iterations, how long each save blocked the
    loop, and the time of a plain ``torch.save`` of the same state, for reference.

    ``barrier``: a directory where each of ``parties`` runs started side by side checks in after its warm-up and
    waits for the others, so that their timed iterations run at the same time."""

    def __init__(self, path: str, warmup: int = WARMUP, barrier: str | None = None, parties: int = 1) -> None:
        self.path = path
        self.warmup = warmup
        self.barrier = barrier
        self.parties = parties
        self.start: tuple[float, float] | None = None
        self.last: tuple[float, float] | None = None
        self.blocking: list[float] = []
        self.iterations: list[tuple[float, float]] = []
        """(seconds, env steps) of each timed iteration, save included."""
        self.phases: dict[str, list[float]] = {}
        self.sent_kb: list[tuple[float, float]] = []
        """What a rank put into collectives in each timed iteration, the mean over ranks and the most (``comm_sent_kb``,
        ``comm_sent_max_kb``)."""

    def after_iteration(self, trainer, metrics: dict[str, float]) -> None:
        if trainer.iteration == self.warmup and self.barrier is not None:
            _meet(Path(self.barrier), Path(self.path).stem, self.parties)
        now = (time.perf_counter(), metrics["env_steps"])
        if trainer.iteration == self.warmup:
            self.start = now
        elif self.start is not None:
            self.blocking.append(trainer.checkpointer.last_blocking_s)
            trainer.checkpointer.last_blocking_s = 0.0
            self.steps_per_s = (now[1] - self.start[1]) / (now[0] - self.start[0])
            self.iterations.append((now[0] - self.last[0], now[1] - self.last[1]))
            self.sent_kb.append((metrics["comm_sent_kb"], metrics["comm_sent_max_kb"]))
            for name, value in metrics.items():
                if name.startswith("time/"):
                    self.phases.setdefault(name.removeprefix("time/").removesuffix("_ms"), []).append(value)
        self.last = now

    def on_end(self, trainer) -> None:
        import torch  # here, as each library below: ``launch/bench_*.py --help`` and the cases not run stay cheap

        if not trainer.info.is_main:
            return
        state = {"common": trainer.common_state(), "rank": trainer.rank_state()}
        started = time.perf_counter()
        torch.save(state, Path(self.path).with_suffix(".pt"))
        torch_save_s = time.perf_counter() - started
        saves = [seconds for seconds in self.blocking if seconds > 0]
        seconds = statistics.median(seconds for seconds, _ in self.iterations)
        steps = statistics.median(steps for _, steps in self.iterations)
        result = {
            "steps_per_s": self.steps_per_s,
            "median_steps_per_s": steps / seconds,
            "blocking_s": saves,
            "torch_save_s": torch_save_s,
            "phases_ms": {name: statistics.mean(values) for name, values in self.phases.items()},
            "sent_kb": statistics.median(mean for mean, _ in self.sent_kb),
            "sent_max_kb": statistics.median(most for _, most in self.sent_kb),
            "transport": trainer.run_description["transport"],
            "fallbacks": trainer.comm.fallbacks,
        }
        replace_text(self.path, json.dumps(result))


def _meet(barrier: Path, name: str, parties: int, timeout: float = 600.0) -> None:
    """Check in at ``barrier`` and wait until ``parties`` have (a file each: the runs share nothing else)."""
    barrier.mkdir(parents=True, exist_ok=True)
    (barrier / name).touch()
    deadline = time.monotonic() + timeout
    while len(list(barrier.iterdir())) < parties:
        if time.monotonic() > deadline:
            raise TimeoutError(f"{parties} side-by-side runs did not all reach {barrier} within {timeout:.0f} s")
        time.sleep(0.01)


def _timed(step_count: int, work) -> float:
    start = time.perf_counter()
    work()
    return step_count / (time.perf_counter() - start)


def measure_raw(iterations: int, setting: Setting) -> float:
    import gymnasium as gym
    import numpy as np

    envs = gym.make_vec(ENV_ID, num_envs=NUM_ENVS, vectorization_mode="sync")
    envs.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, size=(iterations * setting.steps, NUM_ENVS, envs.single_action_space.shape[0]))

    def work() -> None:
        for action in actions:
            envs.step(action)

    return _timed(iterations * setting.steps * NUM_ENVS, work)


def measure_rsl_rl(iterations: int, setting: Setting) -> float:
    import contextlib
    import io

    from rsl_rl.runners import OnPolicyRunner

    from ftrain.train.envs import MujocoVecEnv

    env = MujocoVecEnv(ENV_ID, NUM_ENVS, seed=0)
    model = {
        "class_name": "MLPModel",
        "hidden_dims": list(setting.hidden),
        "activation": setting.activation,
        "obs_normalization": True,
    }
    algorithm = {"num_learning_epochs": setting.epochs, "num_mini_batches": setting.minibatches}
    train_cfg = {
        "num_steps_per_env": setting.steps,
        "save_interval": 10**9,
        "obs_groups": {"actor": ["policy"], "critic": ["policy"]},
        "actor": {**model, "distribution_cfg": {"class_name": "GaussianDistribution", "init_std": 1.0}},
        "critic": model,
        "algorithm": {"class_name": "PPO", **algorithm},
    }
    with contextlib.redirect_stdout(io.StringIO()):
        runner = OnPolicyRunner(env, train_cfg, log_dir=None, device="cpu")
        runner.learn(WARMUP)
        return _timed(iterations * setting.steps * NUM_ENVS, lambda: runner.learn(iterations))


def measure_sb3(iterations: int, setting: Setting) -> float:
    import torch
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env(ENV_ID, n_envs=NUM_ENVS, seed=0)
    activation = {"elu": torch.nn.ELU, "relu": torch.nn.ReLU, "tanh": torch.nn.Tanh}[setting.activation]
    model = PPO(
        "MlpPolicy",
        env,
        n_steps=setting.steps,
        batch_size=NUM_ENVS * setting.steps // setting.minibatches,
        n_epochs=setting.epochs,
        policy_kwargs={"net_arch": list(setting.hidden), "activation_fn": activation},
        device="cpu",
        seed=0,
    )
    model.learn(WARMUP * setting.steps * NUM_ENVS)
    steps = iterations * setting.steps * NUM_ENVS
    return _timed(steps, lambda: model.learn(steps, reset_num_timesteps=False))


def run_ftrain(
    iterations: int, ranks: int, storage: str | None = None, overrides: tuple[str, ...] = (), env: dict | None = None
) -> dict:
    """``ftrain train`` on the HalfCheetah config, measured by :class:`ThroughputHook`; its JSON report."""
    return run_side_by_side(iterations, [ranks], storage, overrides, env)[0]


def throughput_args(
    iterations: int,
    out: Path,
    storage: str,
    log_dir: Path,
    overrides: tuple[str, ...] = (),
    hook: str = "",
    config: Path = CONFIG,
) -> list[str]:
    """``ftrain train``'s arguments for a throughput run of ``config`` (default: the shipped HalfCheetah one), no
    checkpoint or evaluation in the timed window: :class:`ThroughputHook` writes its JSON report to ``out`` (``hook``:
    more of its keyword arguments, YAML)."""
    kwargs = f"path: '{out}'" + (f", {hook}" if hook else "")
    return [
        str(config),
        "--storage",
        storage,
        f"iterations={WARMUP + iterations}",
        f"checkpoint.interval={10**6}",
        f"log_dir={log_dir}",
        "log.console=false",
        "log.tensorboard=false",
        "log.csv=false",
        "eval.every=0",
        f"hooks=[{{target: 'ftrain.tools.bench:ThroughputHook', kwargs: {{{kwargs}}}}}]",
        *overrides,
    ]


def run_side_by_side(
    iterations: int,
    ranks: list[int],
    storage: str | None = None,
    overrides: tuple[str, ...] = (),
    env: dict | None = None,
    config: Path = CONFIG,
) -> list[dict]:
    """One ``ftrain train`` run of ``config`` per entry of ``ranks`` (its rank count), all started at once, whose timed
    iterations begin together (:class:`ThroughputHook`'s barrier); their JSON reports. ``storage``: the one run's, if
    only one."""
    with tempfile.TemporaryDirectory() as tmp:
        runs = []
        for index, count in enumerate(ranks):
            out = Path(tmp) / f"throughput-{index}.json"
            run, logs = storage or str(Path(tmp) / f"run-{index}"), Path(tmp) / f"logs-{index}"
            barrier = f"barrier: '{Path(tmp) / 'barrier'}', parties: {len(ranks)}"
            args = throughput_args(iterations, out, run, logs, overrides, barrier, config)
            launcher = ["-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={count}", "-m", "ftrain"]
            cmd = [sys.executable, *(launcher if count > 1 else ["-m", "ftrain"]), "train", *args]
            environment = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
            with out.with_suffix(".log").open("w") as log:  # not a pipe: a full one would stall a run, and the barrier
                streams = {"stdout": log, "stderr": subprocess.STDOUT}
                process = subprocess.Popen(cmd, env=environment, start_new_session=True, **streams)
                runs.append((process, out))
        while (codes := [process.poll() for process, _ in runs]).count(None) and not any(codes):
            time.sleep(0.2)  # all running, or all done well
        failed = [(process, out) for process, out in runs if process.returncode]
        for process, _ in runs:  # one failed: the others (torchrun and its workers) would wait for it at the barrier
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
        for process, out in failed:
            output = out.with_suffix(".log").read_text()[-4000:]
            raise subprocess.CalledProcessError(process.returncode, process.args, output)
        return [json.loads(out.read_text()) for _, out in runs]


def measure_ftrain(iterations: int, setting: Setting, ranks: int) -> float:
    return run_ftrain(iterations, ranks, overrides=tuple(setting.overrides()))["steps_per_s"]


CASES = {
    "raw": measure_raw,
    "rsl_rl": measure_rsl_rl,
    "sb3": measure_sb3,
    "ftrain-1": lambda n, setting: measure_ftrain(n, setting, 1),
    "ftrain-2": lambda n, setting: measure_ftrain(n, setting, 2),
}


def case_command(name: str, iterations: int, setting_name: str) -> list[str]:
    """The command of a fresh process that runs case ``name`` and prints its steps/s: one torch thread, and MuJoCo's
    warnings routed as ``ftrain train`` routes them (``ftrain.policy.mujoco_warnings``), so that gymnasium's own envs
    (raw, sb3) append no ``MUJOCO_LOG.TXT`` to the working directory."""
    code = "from ftrain.policy.mujoco_warnings import route_mujoco_warnings; route_mujoco_warnings(); "
    code += "import torch; torch.set_num_threads(1); from ftrain.tools.bench import CASES, SETTINGS; "
    code += f"print(CASES[{name!r}]({iterations}, SETTINGS[{setting_name!r}]()))"
    return [sys.executable, "-c", code]


def run_benchmark(iterations: int, settings: list[str]) -> int:
    """Run every case of every setting in a fresh process, print steps/s and the ratios the targets are stated in."""
    if iterations < 1:
        raise UserError(f"--iterations {iterations}: time at least 1 iteration per case")
    return max(_run_setting(iterations, name) for name in settings)


def _run_setting(iterations: int, setting_name: str) -> int:
    setting = SETTINGS[setting_name]()
    print(f"setting {setting_name}: {setting}", flush=True)
    results = {}
    progress = Progress()
    for number, name in enumerate(CASES, start=1):
        progress.show(f"running case {number}/{len(CASES)}: {name} ({iterations} iterations)...")
        done = subprocess.run(
            case_command(name, iterations, setting_name),
            capture_output=True,
            text=True,
            env={**os.environ, "OMP_NUM_THREADS": "1"},
        )
        progress.clear()
        if done.returncode:
            print(f"{name:>9}: failed\n{done.stderr[-2000:]}")
            continue
        results[name] = float(done.stdout.strip().splitlines()[-1])
        print(f"{name:>9}: {results[name]:>8,.0f} steps/s", flush=True)
    peers = [results[name] for name in ("rsl_rl", "sb3") if name in results]
    if peers:
        best = max(peers)
        for name in ("ftrain-1", "ftrain-2"):
            if name in results:
                print(f"{name} / fastest peer: {results[name] / best:.2f}x")
    if "raw" in results and "ftrain-1" in results:
        print(f"ftrain-1 / raw stepping: {results['ftrain-1'] / results['raw']:.2f}x")
    return 0 if len(results) == len(CASES) else 1
