"""The training loop: rollout, returns, update, around rsl-rl's PPO, with hooks, heartbeats and checkpoints.

One ``Trainer`` per rank. Everything that decides what is trained comes from the config and the per-rank seeds;
wall-clock time only feeds logs and heartbeats.
"""

from __future__ import annotations

import collections
import json
import math
import os
import signal
import time
import typing
from pathlib import Path

import torch
import yaml

from ftrain import errorfile
from ftrain.ckpt.claim import claim
from ftrain.ckpt.format import learned_state, state_digest
from ftrain.ckpt.lease import LeaseHeld, LeaseLost
from ftrain.ckpt.manager import Checkpointer
from ftrain.ckpt.resume import CheckpointError
from ftrain.ckpt.storage import StorageUnavailable
from ftrain.comm import group
from ftrain.config import Config, for_launch
from ftrain.errors import EXIT_STORAGE_DOWN, EXIT_STORAGE_HELD, UserError, stop_code
from ftrain.files import replace_text
from ftrain.heartbeat import ENV_DIR, NODE_ENV, HeartbeatWriter, Phase, read_stop_reason
from ftrain.policy.model import action_std
from ftrain.policy.noise_ceiling import build_noise_ceiling
from ftrain.policy.robot import unsaved_state_notice
from ftrain.train import topology
from ftrain.train.env_build import BuildWatch, TooLarge, agree
from ftrain.train.envs import MujocoVecEnv, take_rows
from ftrain.train.evaluation import EvalHook
from ftrain.train.hooks import ConsoleHook, CsvHook, Hook, Hooks, TensorBoardHook, load_hook
from ftrain.train.lr_schedule import build_lr_schedule, horizon_notice
from ftrain.train.phases import Phases
from ftrain.train.ppo import build_algorithm, load_learned_state
from ftrain.train.reward_norm import build_reward_normalizer
from ftrain.train.same_run import check_same_run
from ftrain.train.snapshot_hook import PolicySnapshotHook
from ftrain.train.stop import StopRequest
from ftrain.train.tracking import TrackingHook

EXIT_CHECKPOINT = 1
"""Exit code when a checkpoint cannot be saved or loaded (the supervisor restarts; its crash-loop rule stops it)."""
EPISODE_WINDOW = 100
"""Completed episodes per rank that the mean return and length are taken over."""


class Votes(typing.NamedTuple):
    """What the ranks decide together at an iteration boundary: each rank votes by its own signals and clock, the
    votes ride in the iteration's metrics all-reduce, and a vote of any rank carries, so every rank acts alike."""

    stop: int | None
    """Stop here (a rank was asked to): save and exit; the signal that asked, SIGTERM if any rank got one, else
    SIGINT, so that every rank exits with the same code."""
    save: bool
    """Save here (the checkpoint schedule, or a retry after a failed save), unless a rank has as many saves in flight
    as it may, none settled (a storage that hangs): then at a later boundary, so that training goes on meanwhile."""
    store: bool
    """That save goes to the storage, not to the spool alone (which it does while saves fail, between retries)."""
    hold: bool
    """Train no further until this save commits (saves failing, and too much unsaved work)."""


class Trainer:
    def __init__(
        self,
        config: Config,
        info: group.RankInfo,
        stop: StopRequest | None = None,
        lease_lost: typing.Callable[[], str | None] = lambda: None,
    ) -> None:
        """``lease_lost``: why the storage's lease was lost to another run, once it was (rank 0 without a supervisor,
        which holds the lease; a supervisor stops its workers itself)."""
        # env.total_envs shared by this world's ranks (and by the others an elastic launch may resize to)
        config = for_launch(config, info.world_size)
        self.config = config
        self.info = info
        self.stop = stop or StopRequest()
        self.lease_lost = lease_lost
        torch.set_num_threads(config.torch_threads)
        group.seed_all(config.seed)  # identical model initialisation on every rank
        env_seed = self._env_seed()
        self.env = self._build_env(env_seed)
        if notice := unsaved_state_notice(self.env.robot):
            self.log(notice)
        self.phases = Phases()
        self.alg, self.comm = build_algorithm(
            config, self.env, info, self.phases, lambda line: self.log(line, every_rank=True)
        )
        """``comm``: how the ranks meet; the iteration's small collectives go through it too."""
        self.run_description = topology.announce(config, info, self.comm, self.log)  # one line
        self.reward_norm = build_reward_normalizer(config, self.comm)
        self.lr_schedule = build_lr_schedule(config.algorithm)
        self.noise_ceiling = build_noise_ceiling(config)
        if notice := horizon_notice(config.algorithm, config.iterations):
            self.log(notice)
        group.seed_all(group.rank_seed(config.seed, info.rank))  # what else draws (the action noise and the
        # sample orders come from the algorithm's shared generator: the same on every rank)
        self.hooks = build_hooks(config)
        self.iteration = 0
        self.env_steps = 0
        self.episodes: collections.deque[tuple[float, int]] = collections.deque(maxlen=EPISODE_WINDOW)
        self.metrics: dict[str, float] = {}
        nodes = group.all_gather_object(int(os.environ.get(NODE_ENV, "0")), info)  # which nodes this world spans
        self.heartbeat = HeartbeatWriter(os.environ.get(ENV_DIR), info.rank, info.local_rank, info.world_size, nodes)
        self.checkpointer = Checkpointer(config, info, self.log, self.env.robot)
        self.checkpointer.on_commit = lambda step, manifest: self.hooks.call("on_checkpoint", self, step, manifest)
        self.checkpointer.while_waiting = lambda: self.heartbeat.beat(Phase.CHECKPOINT)
        self.checkpointer.stopping = lambda: self.stop.requested
        self._votes = Votes(None, False, False, False)
        self._config_json = json.dumps(config.public_dict())
        """The config as saved in common.pt: one string, made once (the manifest has it as a mapping)."""

    def _build_env(self, seed: int) -> MujocoVecEnv:
        """This rank's environments; every rank raises UserError if they would not fit in memory
        (``ftrain.train.env_build``)."""
        env = self.config.env
        setting = ("env.total_envs", env.total_envs) if env.total_envs else ("env.num_envs", env.num_envs)
        ranks_here = int(os.environ.get("LOCAL_WORLD_SIZE", "1"))
        watch = BuildWatch(env.num_envs, setting, ranks_here, self.log)
        built = refused = None
        try:
            built = MujocoVecEnv(env.id, env.num_envs, seed, env.kwargs, env.imports, built=watch)
        except TooLarge as too_large:
            refused = too_large
        agree(refused, self.info)
        return built

    def log(self, message: str, every_rank: bool = False) -> None:
        """A line of the run's log: from rank 0, or, for what each rank must be seen to agree on, from every rank."""
        if every_rank and self.info.distributed:
            print(f"[ftrain] rank {self.info.rank}: {message}", flush=True)
        elif self.info.is_main:
            print(f"[ftrain] {message}", flush=True)

    # --- state -------------------------------------------------------------------------------------------------

    def common_state(self) -> dict:
        """Identical on every rank; saved once, by rank 0, as ``common.pt``: rsl-rl's own keys at the top level (its
        ``OnPolicyRunner.load()`` opens the file), ftrain's state under ``ftrain``."""
        return {
            **self.alg.save(),
            "iter": self.iteration,
            "infos": None,
            "ftrain": {
                "learning_rate": self.alg.learning_rate,
                "env_steps": self.env_steps,
                "metrics": dict(self.metrics),
                "hooks": self.hooks.state_dict(),
                "config": self._config_json,
                "update": self.run_description["update"]["kind"],
                **(
                    {"shared_rng": self.alg.shared_generator.get_state()}
                    if hasattr(self.alg, "shared_generator")
                    else {}
                ),
                **({"reward_norm": self.reward_norm.common_state()} if self.reward_norm is not None else {}),
                **({"teacher": self.alg.teacher_identity} if hasattr(self.alg, "teacher_identity") else {}),
            },
        }

    def rank_state(self) -> dict:
        """What differs between ranks: environments, random streams, the episode window."""
        return {
            "env": self.env.get_state(),
            "rng": group.rng_state(),
            "episodes": [list(episode) for episode in self.episodes],
            **({"reward_norm": self.reward_norm.rank_state()} if self.reward_norm is not None else {}),
        }

    def rank_state_from(self, shards: list[dict], offset: int) -> dict:
        """This rank's state from consecutive ranks' ``shards`` of a checkpoint of another world size: its
        environments are theirs from row ``offset`` on (``env.total_envs``: each goes on by its global index); the
        random streams and the episode window are the first shard's."""
        count = self.config.env.num_envs
        state = {**shards[0], "env": take_rows([shard["env"] for shard in shards], offset, count)}
        if "reward_norm" in shards[0]:  # each environment's discounted return so far
            state["reward_norm"] = torch.cat([shard["reward_norm"] for shard in shards])[offset : offset + count]
        return state

    def load_state(self, common: dict, rank: dict | None, saved: dict) -> None:
        """``rank``: this rank's shard, None for a rank the checkpoint did not have; ``saved``: the checkpoint's
        config (see ``ftrain.ckpt.resume``)."""
        own = common["ftrain"]
        load_learned_state(self.alg, common, self._resumed_learning_rate(own["learning_rate"], saved["algorithm"]))
        self.iteration = common["iter"]
        self.env_steps = own["env_steps"]
        self.metrics = dict(own["metrics"])
        self.hooks.load_state_dict(own["hooks"])
        if self.reward_norm is not None and "reward_norm" in own:  # absent: resumed with allow_config_change
            returns = rank["reward_norm"] if rank is not None else torch.zeros_like(self.reward_norm.returns)
            self.reward_norm.load_state(own["reward_norm"], returns)
        if "teacher" in own:  # the teacher's weights come from the checkpoint: so does its identity
            if own["teacher"]["digest"] != self.alg.teacher_identity["digest"]:
                self.log(
                    f"teacher={self.config.teacher} is not the teacher this run started with: it keeps that one, "
                    "from its checkpoint"
                )
                self.alg.teacher_identity = own["teacher"]
            else:  # the same teacher: a checkpoint of before its config was kept gets it from the one loaded
                self.alg.teacher_identity = {**self.alg.teacher_identity, **own["teacher"]}
        reseeded = saved["seed"] != self.config.seed  # let through at this resume: the random streams start anew
        if hasattr(self.alg, "shared_generator"):  # (absent: a checkpoint of before the shared stream)
            shared = None if reseeded else own.get("shared_rng")
            if shared is not None:
                self.alg.shared_generator.set_state(shared)
            else:
                self.alg.shared_generator.manual_seed(group.run_seed(self.config.seed, "update", self.iteration))
        update = self.run_description["update"]
        if own.get("update", update["kind"]) != update["kind"]:
            now = topology.update_words(update)
            self.log(f"the update was {own['update']} until step {self.iteration}; from here on: {now}")
        if rank is None:  # a rank that joins a resized run: environments and random streams of its own
            self.env.reset(self._env_seed(self.iteration))
            group.seed_all(group.rank_seed(self.config.seed, self.info.rank, self.iteration))
            self.episodes.clear()
            return
        self.env.set_state(rank["env"])
        group.set_rng_state(rank["rng"])
        self.episodes.clear()
        self.episodes.extend((float(ret), int(length)) for ret, length in rank["episodes"])
        if reseeded:
            self.env.reseed(self._env_seed(self.iteration))
            group.seed_all(group.rank_seed(self.config.seed, self.info.rank, self.iteration))

    def _resumed_learning_rate(self, rate: float, saved: dict) -> float:
        """The learning rate a resume goes on with: the checkpoint's ``rate`` (the adaptive schedule's), unless the
        config's rate or schedule changed at this resume (``allow_config_change``): then the config's, as a start's
        (a linear schedule sets it again every iteration)."""
        now = self.config.algorithm
        changed = (saved.get("learning_rate"), saved.get("schedule")) != (now.learning_rate, now.schedule)
        return now.learning_rate if changed else rate

    def _env_seed(self, *at_step: int) -> int:
        """The seed of this rank's first environment (of a fresh start, or of a rank joining at ``at_step``): by its
        global index, so that an environment is seeded alike whatever the number of ranks."""
        return group.env_seed(self.config.seed, self.info.rank * self.config.env.num_envs, *at_step)

    def learned_digest(self) -> str:
        """What a checkpoint of this state records as ``state_sha256``."""
        return state_digest(learned_state(self.alg.save()))

    # --- loop --------------------------------------------------------------------------------------------------

    def run(self) -> int:
        self.stop.training()
        self.heartbeat.beat(Phase.START, 0)
        resumed = self.checkpointer.restore(self)
        if hasattr(self.alg, "teacher_identity"):  # which teacher a distillation learns from: a resumed one, its own
            if not self.alg.teacher_loaded:  # gone, and no step of this run restored to take its weights from
                raise UserError(self.alg.teacher_missing)
            teacher = self.alg.teacher_identity
            if self.alg.teacher_missing:
                self.log(f"{self.alg.teacher_missing}; the run goes on with the teacher its checkpoint holds")
            self.log(f"teacher: {teacher['source']} (step {teacher['step']}, state_sha256 {teacher['digest'][:16]})")
        if resumed is None and self.info.distributed:
            self.alg.broadcast_parameters()
        self.heartbeat.resumed_step = resumed
        self.heartbeat.config_change = self.checkpointer.config_change
        if idle := self.iteration >= self.config.iterations:
            self.log(
                f"nothing to train: the run is already at step {self.iteration}, asked for iterations="
                f"{self.config.iterations} (pass iterations=N with N > {self.iteration} to train on)"
            )
            if self.checkpointer.committed_step != self.iteration:  # it came from the spool: the storage must have it
                self.checkpointer.save(self, hold=True)
        committed = self.checkpointer.committed_step
        self.heartbeat.committed_step = resumed if committed is None else committed
        if not idle:  # a start that trains nothing leaves the trained run's record as it was
            self._write_resolved_config()
        self.alg.train_mode()
        self.hooks.call("on_start", self)
        self.hooks.check_state()
        self.heartbeat.beat(Phase.START, self.iteration)
        self.phases.take()  # the first row counts from here, not from start-up
        while self.iteration < self.config.iterations:
            self._iterate()
            stop, last = self._votes.stop is not None, self.iteration == self.config.iterations
            if stop or last or self._votes.save:
                self.heartbeat.beat(Phase.CLOSING if stop or last else Phase.CHECKPOINT, self.iteration)
                hold = stop or last or self._votes.hold
                self.checkpointer.save(self, wait=stop, hold=hold, store=self._votes.store)
                self.heartbeat.committed_step = self.checkpointer.committed_step
            if stop:
                code = stop_code(self._votes.stop)
                self.log(
                    f"stopped by {_stop_name(self._votes.stop)}: saved step {self.iteration}, exiting with code {code}"
                )
                self.stop.exiting()
                break
        self.checkpointer.close()
        self.heartbeat.committed_step = self.checkpointer.committed_step
        self.hooks.call("on_end", self)
        self.heartbeat.beat(Phase.PREEMPTED if self.iteration < self.config.iterations else Phase.DONE, self.iteration)
        if self.iteration < self.config.iterations and self._votes.stop is not None:
            return stop_code(self._votes.stop)
        return 0

    def _iterate(self) -> None:
        start = time.perf_counter()
        self.heartbeat.beat(Phase.ROLLOUT, self.iteration)
        if self.noise_ceiling is not None:  # before the rollout: its noise is the update's
            self.noise_ceiling.apply(self.alg.get_policy().distribution, self.iteration)
        self._collect()
        if self.reward_norm is not None:
            with self.phases("sync_rewards"):  # an all-reduce of the returns' moments: where the ranks first meet
                self.reward_norm.update()
        self.hooks.call("after_rollout", self)
        collected = time.perf_counter()
        self.heartbeat.beat(Phase.UPDATE)
        if self.lr_schedule is not None:
            self.lr_schedule.apply(self.alg, self.iteration)
        with self.phases("update"):
            losses = self.alg.update()
        self.hooks.call("after_update", self, losses)
        learned = time.perf_counter()
        self.iteration += 1
        self._record_metrics(losses, collected - start, learned - collected)
        self.hooks.call("after_iteration", self, self.metrics)

    def _collect(self) -> None:
        """One rollout of ``num_steps_per_env`` steps into the algorithm's storage, then its returns."""
        phase = self.phases
        obs = self.env.get_observations()
        with torch.inference_mode():
            for _ in range(self.config.num_steps_per_env):
                with phase("policy"):
                    actions = self.alg.act(obs)
                with phase("env"):
                    obs, rewards, dones, extras = self.env.step(actions)
                with phase("buffer"):
                    if self.reward_norm is not None:
                        rewards = self.reward_norm(rewards, dones)
                    self.alg.process_env_step(obs, rewards, dones, extras)
                    self.episodes.extend(zip(*extras["episodes"], strict=True))
            with phase("buffer"):
                self.alg.compute_returns(obs)

    def _record_metrics(self, losses: dict[str, float], collect_time: float, learn_time: float) -> None:
        """Global metrics: the episode window, the step count, the votes (see ``Votes``), the bytes sent and the phases'
        times of every rank are gathered in one collective and summed; of the bytes and the phases, the mean over ranks
        and the largest."""
        returns = sum(ret for ret, _ in self.episodes)
        lengths = sum(length for _, length in self.episodes)
        steps = self.env.num_envs * self.config.num_steps_per_env
        stops = (self.stop.signal == signal.SIGTERM, self.stop.signal == signal.SIGINT)
        votes = (*stops, *self.checkpointer.votes(self.iteration), self.lease_lost() is not None)
        phases = self.phases.take()
        sent_kb = self.comm.take_sent() / 1024  # (the iteration's collectives, this gather's of the one before)
        with self.phases("sync_metrics"):
            every = self.comm.gather_values(
                [returns, lengths, len(self.episodes), steps, *map(float, votes), sent_kb, *phases.values()]
            )
        total_returns, total_lengths, count, total_steps, *summed = every.sum(dim=0).tolist()
        terms, ints, save, store, hold, busy, lost = (vote > 0 for vote in summed[: len(votes)])
        if lost:  # another run took the storage's lease: every rank stops here alike; rank 0 knows why
            raise LeaseLost(self.lease_lost() or "another run took the storage's lease (rank 0 says which)")
        total_sent, *phase_totals = summed[len(votes) :]
        mean = (total / self.info.world_size for total in phase_totals)
        slowest = every[:, -len(phases) :].max(dim=0).values.tolist()
        phase_ms = {f"time/{name}_ms": 1000 * seconds for name, seconds in zip(phases, mean, strict=True)}
        phase_ms |= {f"time/{name}_max_ms": 1000 * seconds for name, seconds in zip(phases, slowest, strict=True)}
        stop = signal.SIGTERM if terms else signal.SIGINT if ints else None
        self._votes = Votes(stop, save and (hold or not busy), store, hold)
        self.env_steps += int(total_steps)
        previous = self.metrics
        iteration_time = collect_time + learn_time
        self.metrics = {
            "mean_return": total_returns / count if count else previous.get("mean_return", math.nan),
            "mean_length": total_lengths / count if count else previous.get("mean_length", math.nan),
            "env_steps": float(self.env_steps),
            "world_size": float(self.info.world_size),
            **{f"loss/{key}": value for key, value in losses.items()},
            "learning_rate": self.alg.learning_rate,
            "action_std": action_std(self.alg.get_policy()),
            "steps_per_s": total_steps / iteration_time,
            "collect_time": collect_time,
            "learn_time": learn_time,
            "iteration_time": iteration_time,
            "update_split": float(self.run_description["update"]["kind"] == "split"),
            "comm_fallbacks": float(self.comm.fallbacks),
            "comm_sent_kb": total_sent / self.info.world_size,
            "comm_sent_max_kb": every[:, -len(phases) - 1].max().item(),
            **phase_ms,
        }

    def _write_resolved_config(self) -> None:
        """``config.yaml`` and ``run.json``: what this run is, once it has a step to start from and one to train."""
        if self.info.is_main:
            log_dir = Path(self.config.log_dir)
            log_dir.mkdir(parents=True, exist_ok=True)
            replace_text(log_dir / "config.yaml", yaml.safe_dump(self.config.saved_dict(), sort_keys=False))
            topology.write(log_dir, self.run_description)


def build_hooks(config: Config) -> Hooks:
    """Built-in hooks in the order their outputs feed each other (evaluation adds ``eval_return`` to the metrics
    that the logging hooks then write), then the user's hooks from the config."""
    hooks: list[Hook] = []
    if config.eval.every:
        hooks.append(EvalHook(config.eval))
    hooks.append(ConsoleHook(every_save=config.log.console_saves == "every", lines=config.log.console))
    if config.log.tensorboard:
        hooks.append(TensorBoardHook())
    if config.log.csv:
        hooks.append(CsvHook())
    if config.log.wandb.enabled or config.log.mlflow.enabled:
        hooks.append(TrackingHook(config))
    if config.snapshots.every:
        hooks.append(PolicySnapshotHook(config.snapshots))
    user = []
    for hook_config in config.hooks:
        hook = load_hook(hook_config.target, hook_config.kwargs)
        hook.every = hook_config.every
        user.append(hook)
    return Hooks(hooks, user)


def train(config: Config) -> int:
    """Entry point of ``ftrain train`` on every rank: 0 when done, 143 or 130 when stopped by SIGTERM or SIGINT (and
    saved), 1 when checkpoints fail, 7 when the storage does not answer, 8 when another run holds the storage
    (``ftrain.ckpt.lease``: rank 0 holds it for the run, or its supervisor does), or took it from this run (at the
    next iteration boundary after rank 0's renewal finds it)."""
    stop = StopRequest()
    stop.install(_stopped_while_starting)
    info = group.init(config.dist_timeout)
    trainer = claimed = None
    try:
        check_same_run(config, info)  # before the lease is taken: nodes started apart may have been told otherwise
        claimed = claim(config, info.is_main, lambda outcome: group.broadcast_object(outcome, info), _say)
        trainer = Trainer(config, info, stop, lambda: claimed.lost)
        return trainer.run()
    except LeaseHeld as held:  # another run holds the storage, or took it: nothing more of it touched
        errorfile.report(str(held))
        return EXIT_STORAGE_HELD
    except CheckpointError as error:
        errorfile.report(str(error))
        return EXIT_CHECKPOINT
    except StorageUnavailable as error:
        errorfile.report(str(error))
        return EXIT_STORAGE_DOWN
    finally:
        if trainer is not None:
            trainer.checkpointer.shutdown()
        if claimed is not None:
            claimed.release()
        group.shutdown()


def _stopped_while_starting(signum: int) -> None:
    line = f"stopped by {_stop_name(signum)} while starting, before any training: nothing to save"
    errorfile.record_stop(line)
    if errorfile.says_its_stop():
        _say(line)


def _stop_name(signum: int) -> str:
    """The signal's name, or what the user sent where a supervisor stops the run for them."""
    return read_stop_reason(os.environ.get(ENV_DIR)) or signal.Signals(signum).name


def _say(line: str) -> None:
    print(f"[ftrain] {line}", flush=True)
