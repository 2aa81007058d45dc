"""Play: roll a policy out in its environment, print the returns, optionally render a video headless."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ftrain.errors import UserError, counted
from ftrain.policy.load import Policy, check_fits
from ftrain.policy.options import check_play_options
from ftrain.policy.robot import make_env
from ftrain.policy.rollout import Episode, rollout
from ftrain.progress import Progress


@dataclass
class PlayResult:
    returns: list[float]
    lengths: list[int]
    frames: int
    """Video frames written: one per observation, ``sum(length + 1)`` (0 without a video)."""


def play(
    policy: Policy, episodes: int = 1, deterministic: bool = True, video: str | Path | None = None, seed: int = 0
) -> PlayResult:
    """Roll ``policy`` out for ``episodes`` episodes (seeded ``seed``, ``seed + 1``, ...) in an environment of its
    own; print each return and the mean. It takes the mean action, as rsl-rl's and IsaacLab's play do, unless not
    ``deterministic`` (then actions are sampled, seeded by ``seed``). ``video`` (``.mp4`` or ``.gif``) renders it
    headless (MUJOCO_GL=egl)."""
    check_play_options(episodes, seed, video)
    if video is not None:
        os.environ.setdefault("MUJOCO_GL", "egl")  # read when the first renderer is made: headless, no display
    if not deterministic and policy.exported is not None:
        raise UserError(
            f"--stochastic: {policy.source} is an exported {policy.exported} policy, which has only its mean actions: "
            "play its checkpoint or policy snapshot to sample"
        )
    mode = "deterministic (mean) actions" if deterministic else "sampled actions"
    rendered = "" if video is None else f", drawing every frame into {video} (far slower than playing alone)"
    print(f"playing {policy.source} (step {policy.step}, {policy.config.env.id}) with {mode}{rendered}", flush=True)
    torch.manual_seed(seed)
    env = make_env(policy.config.env, render=video is not None)
    check_fits(policy, env)
    writer = None if video is None else _VideoWriter(Path(video), env)
    progress = _PlayProgress(episodes, env.spec.max_episode_steps, writer)  # set: robot.check_trainable

    def observed(obs: np.ndarray) -> None:
        if writer is not None:
            writer.add_frame(obs)
        progress.observed()

    def finished(index: int, episode: Episode) -> None:
        progress.episode_ended()
        print(f"episode {index}: return {episode.ret:.2f}, length {episode.length}", flush=True)

    results = None
    try:
        act = lambda obs: policy.act(obs, deterministic)  # noqa: E731
        size = policy.config.eval.episodes  # evaluation's layout: its episode i returns here what it scored there
        rows = (0, size) if deterministic and episodes <= size else None
        results = rollout(env, act, episodes, seed, on_observation=observed, on_episode=finished, rows=rows)
    finally:
        progress.progress.clear()
        env.close()
        if writer is not None:
            writer.close(keep=results is not None)
    returns = [episode.ret for episode in results]
    print(f"mean return over {counted(episodes, 'episode')}: {np.mean(returns):.2f} (std {np.std(returns):.2f})")
    frames = 0 if writer is None else writer.frames
    if writer is not None:
        height, width = writer.size
        print(f"video: {video} ({frames} frames of {width}x{height} at {writer.fps:g} fps)")
    return PlayResult(returns, [episode.length for episode in results], frames)


class _PlayProgress:
    """The live line of a play on a terminal: steps (video frames) so far, of at most what the episodes' step limit
    allows, with an ETA; an episode that ends early brings the end nearer."""

    def __init__(self, episodes: int, limit: int, writer: _VideoWriter | None) -> None:
        self.progress = Progress()
        self.episodes = episodes
        self.limit = limit
        self.label = f"rendering {writer.path.name}" if writer is not None else "playing"
        self.unit = "frames" if writer is not None else "steps"
        self.seen = 0
        """Observations so far: after each reset and each step, as the video's frames."""
        self.ended = 0
        self._ended_at = 0

    def observed(self) -> None:
        self.seen += 1
        episode = f" (episode {min(self.ended + 1, self.episodes)} of {self.episodes})"
        total = self._ended_at + (self.episodes - self.ended) * (self.limit + 1)
        self.progress.count(self.label, self.seen, total, self.unit, episode)

    def episode_ended(self) -> None:
        self.ended += 1
        self._ended_at = self.seen
        self.progress.clear()


class _VideoWriter:
    """Renders the environment at every observation and streams the frames to an mp4 (ffmpeg) or a gif, in a file
    of its own beside ``path`` that becomes ``path`` once every episode is in: a play stopped part way (Ctrl-C, an
    error) leaves no video cut short, and whatever ``path`` held before."""

    def __init__(self, path: Path, env) -> None:
        import imageio.v2 as imageio

        self.env = env
        self.path = path
        self.partial = path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")
        self.fps = float(env.metadata.get("render_fps", 30))
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.suffix.lower() == ".gif":
            self.writer = imageio.get_writer(self.partial, mode="I", duration=1000 / self.fps, loop=0)
        else:
            self.writer = imageio.get_writer(self.partial, fps=self.fps)
        self.frames = 0
        self.size = (0, 0)

    def add_frame(self, obs: np.ndarray) -> None:
        try:
            frame = self.env.render()
        except Exception as exc:  # no usable OpenGL: the error type depends on the backend and what is missing
            raise UserError(
                f"headless rendering failed ({type(exc).__name__}: {exc}): install Debian's Mesa EGL "
                "(apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0) and keep MUJOCO_GL=egl"
            ) from None
        self.writer.append_data(frame)
        self.frames += 1
        self.size = frame.shape[:2]

    def close(self, keep: bool) -> None:
        """``keep``: every episode is in, the video goes to its path; else it goes."""
        try:
            self.writer.close()
        except BaseException:
            keep = False
            raise
        finally:
            if keep:
                os.replace(self.partial, self.path)
            else:
                self.partial.unlink(missing_ok=True)
