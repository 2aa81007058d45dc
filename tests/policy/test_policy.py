"""Policies from a real training run: loading, export that runs without ftrain, play with video, bad input."""

from __future__ import annotations

import hashlib
import random
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import onnx
import pytest
import torch
from rsl_rl.modules import EmpiricalNormalization
from tensordict import TensorDict

from ftrain.cli import main
from ftrain.config import load_config
from ftrain.errors import UserError, load_error_line
from ftrain.policy.export import export, sample_observations
from ftrain.policy.load import load_policy
from ftrain.policy.model import OBS_GROUP, ClippedNormalization, build_actor
from ftrain.policy.play import play

from helpers import (
    REPO,
    SMOKE,
    as_a_terminal_starts_it,
    child_env,
    final_manifest,
    finish,
    flip_byte,
    launch,
    needs_egl,
    on_a_terminal,
    run_train,
    wait_for,
)

pytestmark = pytest.mark.slow  # every test plays or exports a policy trained first

EPISODE_STEPS = 20
STANDALONE = r"""
import sys
sys.modules.update(ftrain=None, rsl_rl=None)  # importing either now fails: the exported files must not need them
import numpy as np, onnxruntime, torch
obs = np.load(sys.argv[1])
torchscript = torch.jit.load(sys.argv[2])(torch.from_numpy(obs)).detach().numpy()
onnx = onnxruntime.InferenceSession(sys.argv[3]).run(None, {"obs": obs})[0]
np.save(sys.argv[4], np.stack([torchscript, onnx]))
"""


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A tiny policy: 4 iterations, checkpoints at steps 2 and 4, episodes of 20 steps, normalised observations
    clipped at 1 (so that the exports must clip too)."""
    run = tmp_path_factory.mktemp("policy") / "run"
    run_train(run, "iterations=4", f"env.kwargs={{max_episode_steps: {EPISODE_STEPS}}}", "policy.obs_clip=1.0")
    return run


def step_url(run: Path, step: int) -> str:
    return str(run / "checkpoints" / f"step-{step:09d}")


def test_load_from_a_run_or_a_step(trained) -> None:
    newest = load_policy(str(trained))
    manifest = final_manifest(trained)
    assert (newest.step, newest.digest, newest.exported) == (4, manifest["state_sha256"], None)
    assert newest.source == step_url(trained, 4) and newest.manifest == manifest
    assert newest.config.env.kwargs == {"max_episode_steps": EPISODE_STEPS}
    assert not newest.actor.training

    older = load_policy(step_url(trained, 2))
    assert older.step == 2 and older.digest != newest.digest
    obs = sample_observations(newest)
    assert obs.shape[1] == 17 and len(obs) == 3 * (EPISODE_STEPS + 1)
    assert not torch.equal(older.act(obs), newest.act(obs))
    torch.manual_seed(0)
    assert not torch.equal(newest.act(obs, deterministic=False), newest.act(obs)), "sampling must add noise"


def test_clipped_observation_normalisation_keeps_rsl_rl_state_and_clips(trained) -> None:
    policy = load_policy(str(trained))
    normalizer = policy.actor.obs_normalizer
    assert isinstance(normalizer, ClippedNormalization) and normalizer.clip == 1.0
    plain = EmpiricalNormalization(normalizer._mean.shape[-1])
    plain.load_state_dict(normalizer.state_dict())  # the same buffers: rsl-rl opens ftrain's state
    obs = sample_observations(policy, episodes=1, seed=3) * 50
    assert plain(obs).abs().max() > 1.0
    torch.testing.assert_close(normalizer(obs), plain(obs).clamp(-1.0, 1.0))


def test_exports_run_without_ftrain_and_match_the_actor(trained, tmp_path, capsys) -> None:
    files = {"torchscript": tmp_path / "policy.pt", "onnx": tmp_path / "policy.onnx"}
    for fmt, path in files.items():
        assert main(["export", str(trained), "--format", fmt, "-o", str(path)]) == 0
        printed = capsys.readouterr()
        assert printed.out.startswith(f"wrote {path}: {fmt} policy of step 4") and printed.out.count("\n") == 1
        assert "torch.onnx" not in printed.out + printed.err  # the exporter's progress lines stay off the console
    graph = onnx.load(files["onnx"]).graph  # made by torch.export's exporter (dynamo=True), which labels its inputs
    assert any(prop.key.startswith("pkg.torch.export") for value in graph.input for prop in value.metadata_props)
    axes = [value.type.tensor_type.shape.dim[0].dim_param for value in [*graph.input, *graph.output]]
    assert axes == ["batch"] * len(axes) and len(axes) >= 2, axes
    policy = load_policy(str(trained))
    obs = sample_observations(policy, episodes=2, seed=7)
    np.save(tmp_path / "obs.npy", obs.numpy())
    subprocess.run(
        [sys.executable, "-I", "-c", STANDALONE, "obs.npy", files["torchscript"], files["onnx"], "out.npy"],
        cwd=tmp_path,
        check=True,
    )
    expected = policy.act(obs).numpy()
    for actions in np.load(tmp_path / "out.npy"):
        np.testing.assert_allclose(actions, expected, atol=1e-5, rtol=1e-5)

    for fmt, path in files.items():
        exported = load_policy(str(path))
        assert (exported.exported, exported.step) == (fmt, 4)
        assert exported.digest == hashlib.sha256(path.read_bytes()).hexdigest()
        assert exported.config.to_dict() == policy.config.to_dict()
        torch.testing.assert_close(exported.act(obs), policy.act(obs), atol=1e-5, rtol=1e-5)


def test_an_export_without_a_path_lands_next_to_the_run(trained, tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.chdir(tmp_path)  # where a user runs it from: nothing must land here
    assert main(["export", step_url(trained, 2), "--format", "torchscript"]) == 0
    expected = trained / "exports" / "smoke-step-2.pt"
    assert f"wrote {expected}:" in capsys.readouterr().out
    assert load_policy(str(expected)).step == 2
    assert not [path for path in tmp_path.iterdir() if path.suffix in (".pt", ".onnx")]


def check_video(path: Path, frames: int) -> None:
    decoded = imageio.mimread(path, memtest=False)
    assert len(decoded) == frames
    assert {frame.shape[:2] for frame in decoded} == {(480, 480)}
    assert min(frame[..., :3].std() for frame in decoded) > 10, "a blank frame"
    assert not np.array_equal(decoded[0], decoded[-1]), "nothing moves"


@needs_egl
def test_play_renders_mp4_and_gif(trained, tmp_path, capsys) -> None:
    video = tmp_path / "cheetah.mp4"
    assert main(["play", str(trained), "--episodes", "2", "--video", str(video)]) == 0
    out = capsys.readouterr().out
    lengths = [int(length) for length in re.findall(r"episode \d: return -?[\d.]+, length (\d+)", out)]
    assert lengths == [EPISODE_STEPS, EPISODE_STEPS]
    assert "mean return over 2 episodes" in out and "rendering:" not in out, "a live line only on a terminal"
    check_video(video, sum(length + 1 for length in lengths))  # a frame after the reset and after each step

    gif = tmp_path / "cheetah.gif"
    result = play(load_policy(str(trained)), episodes=1, video=gif)
    assert result.frames == EPISODE_STEPS + 1 and result.lengths == [EPISODE_STEPS]
    check_video(gif, result.frames)


@needs_egl
def test_play_on_a_terminal_counts_frames_with_an_eta_and_prints_each_episode_as_it_ends(trained, tmp_path) -> None:
    command = [sys.executable, "-m", "ftrain", "play", str(trained), "--episodes", "2", "--video", "cheetah.gif"]
    out = on_a_terminal(command, tmp_path)
    # episodes have 21 frames: episode 2's first is frame 22 of at most 42, drawn at once; its last ends the count
    second = re.search(r"\rrendering cheetah\.gif: 22/42 frames \(52%\)(, ETA \d+s)? \(episode 2 of 2\)", out)
    last = re.search(r"\r(rendering cheetah\.gif: 42/42 frames \(100%\), ETA 0s \(episode 2 of 2\))", out)
    assert second and last, repr(out)
    wiped = "\r" + " " * len(last[1]) + "\r"
    assert f"{last[0]}{wiped}episode 2: return" in out, repr(out)
    assert out.index("episode 1: return") < second.start(), "episode 1 must show as it ends"


def test_play_takes_the_mean_action_unless_told_to_sample(trained, capsys) -> None:
    policy = load_policy(str(trained))
    mean, sampled = (play(policy, seed=3, deterministic=deterministic).returns for deterministic in (True, False))
    assert mean != sampled
    assert play(policy, seed=3).returns == mean
    capsys.readouterr()
    for flags, returns, mode in (([], mean, "deterministic (mean) actions"), (["--stochastic"], sampled, "sampled")):
        assert main(["play", str(trained), "--seed", "3", *flags]) == 0
        out = capsys.readouterr().out
        assert f"with {mode}" in out and f"episode 1: return {returns[0]:.2f}," in out


def test_play_an_exported_policy_like_its_checkpoint(trained, tmp_path) -> None:
    path = tmp_path / "policy.onnx"
    assert main(["export", step_url(trained, 2), "--format", "onnx", "-o", str(path)]) == 0
    from_checkpoint = play(load_policy(step_url(trained, 2)), episodes=2, deterministic=True, seed=3)
    from_file = play(load_policy(str(path)), episodes=2, seed=3)  # an exported policy always acts deterministically
    assert from_file.lengths == from_checkpoint.lengths
    assert from_file.returns == pytest.approx(from_checkpoint.returns, rel=1e-4)


def test_a_corrupt_newest_step_is_skipped_and_a_corrupt_step_refused(trained, tmp_path) -> None:
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    flip_byte(Path(step_url(run, 4)) / "common.pt")
    heard: list[str] = []
    assert load_policy(str(run), log=heard.append).step == 2
    assert heard and "skipping checkpoint step 4" in heard[0]
    with pytest.raises(UserError, match="does not verify"):
        load_policy(step_url(run, 4))


def test_bad_input_is_one_line_and_exit_code_2(trained, tmp_path, capsys) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("not a policy\n")
    (tmp_path / "empty").mkdir()
    exported = tmp_path / "policy.onnx"
    assert main(["export", str(trained), "--format", "onnx", "-o", str(exported)]) == 0
    anonymous = onnx.load(exported)
    del anonymous.metadata_props[:]
    onnx.save(anonymous, tmp_path / "anonymous.onnx")
    cases = {
        "a directory without checkpoints": (["play", str(tmp_path / "empty")], "no verified checkpoint under"),
        "a text file": (["play", str(notes)], "is neither a TorchScript nor an ONNX file"),
        "a checkpoint file": (["play", str(Path(step_url(trained, 2)) / "common.pt")], "is not a TorchScript policy"),
        "an ONNX model of someone else": (["play", str(tmp_path / "anonymous.onnx")], "not an ftrain policy"),
        "a step that does not exist": (["play", step_url(trained, 3)], "step-000000003 does not exist: see ftrain"),
        "a path that does not exist": (["play", str(tmp_path / "nowhere")], "nowhere does not exist: pass a run's"),
        "an unknown video format": (["play", str(trained), "--video", "out.avi"], "must end in .mp4 or .gif"),
        "no episodes": (["play", str(trained), "--episodes", "0"], "play at least 1 episode"),
        "a seed gymnasium refuses": (["play", str(trained), "--seed", "-1"], "--seed -1 is out of range: use a seed"),
        "bad options before any policy is looked for": (
            ["play", str(tmp_path / "empty"), "--episodes", "0"],
            "play at least 1 episode",
        ),
        "a video where no file can be made": (
            ["play", str(trained), "--video", "/proc/x.mp4"],
            "cannot write /proc/x.mp4 (/proc takes no new file: No such file or directory): pass --video a path",
        ),
        "a video under a directory that cannot be made": (
            ["play", str(trained), "--video", "/proc/nope/x.mp4"],
            "cannot write /proc/nope/x.mp4 (/proc takes no new file: No such file or directory): pass --video a",
        ),
        "an export where no file can be made": (
            ["export", str(trained), "--format", "onnx", "-o", "/proc/x.onnx"],
            "cannot write /proc/x.onnx (/proc takes no new file: No such file or directory): pass -o a path",
        ),
        "an exported policy to export": (["export", str(exported), "--format", "torchscript"], "exported onnx policy"),
        "an exported policy to sample": (["play", str(exported), "--stochastic"], "which has only its mean actions"),
        "an export of no format": (["export", str(trained)], "export needs --format torchscript or onnx, or -o a"),
        "an export to a file of no format": (
            ["export", str(trained), "-o", str(notes)],
            f"-o {notes}: policy files end in .pt or .onnx: use -o {notes.with_suffix('.pt')} or -o",
        ),
        "an output of another kind": (
            ["export", str(trained), "--format", "onnx", "-o", str(notes)],
            f"-o {notes}: onnx policy files end in .onnx: use -o {notes.with_suffix('.onnx')} or a directory",
        ),
        "an output of the other format": (
            ["export", str(trained), "--format", "onnx", "-o", str(tmp_path / "x.pt")],
            f"onnx policy files end in .onnx: use -o {tmp_path / 'x.onnx'} or a directory, or --format torchscript",
        ),
        "an export into a directory of no format": (
            ["export", str(trained), "-o", f"{tmp_path}/"],
            f"-o {tmp_path}/ is a directory: export into it needs --format torchscript or onnx, or -o a file",
        ),
    }
    for case, (argv, message) in cases.items():
        assert main(argv) == 2, case
        err = capsys.readouterr().err
        assert err.startswith("ftrain: error: ") and err.count("\n") == 1, f"{case}: {err!r}"
        assert message in err, f"{case}: {err!r}"
    assert notes.read_text() == "not a policy\n"  # not written over
    for suffix, fmt in ((".pt", "torchscript"), (".ONNX", "onnx")):  # -o's suffix names the format, in any case
        assert main(["export", str(trained), "-o", str(tmp_path / f"named{suffix}")]) == 0
        assert load_policy(str(tmp_path / f"named{suffix}")).exported == fmt
    assert main(["export", str(trained), "--format", "torchscript", "-o", str(tmp_path)]) == 0  # a directory: into it
    assert load_policy(str(tmp_path / f"smoke-step-{load_policy(str(trained)).step}.pt")).step > 0
    assert main(["export", str(trained), "--format", "onnx", "-o", f"{tmp_path / 'new'}/"]) == 0  # a directory to make
    assert [path.name for path in (tmp_path / "new").iterdir()] == [f"smoke-step-{load_policy(str(trained)).step}.onnx"]
    with pytest.raises(UserError, match="unknown policy format 'tflite': use torchscript or onnx"):
        export(load_policy(str(trained)), "tflite")  # the CLI's --format choices refuse it before (tests/test_cli.py)


def test_no_output_lands_inside_a_step_of_a_storage(trained, tmp_path, capsys) -> None:
    """export's ``-o``, play's ``--video`` and plot's ``-o`` inside a step directory (one of ``checkpoints/``, one
    set aside under ``quarantine/``, a policy snapshot under ``policies/``), named as a shard of it, as the step
    itself, through ``..`` or through a link: one line, exit 2, and every byte of the storage as it was. A torchscript
    export to ``.../common.pt`` replaced the newest step's shard and exited 0."""
    run = tmp_path / "run"
    shutil.copytree(trained, run)
    newest = run / "checkpoints" / "step-000000004"
    for parent in ("quarantine", "policies"):
        shutil.copytree(newest, run / parent / "step-000000004")
    (tmp_path / "link").symlink_to(newest)
    before = {path: path.read_bytes() for path in sorted(run.rglob("*")) if path.is_file()}
    places = []
    for parent in ("checkpoints", "quarantine", "policies"):
        step = run / parent / "step-000000004"
        places += [step / "common.pt", step / "rank-00000.pt", step, step / "sub" / "x.pt"]
    places += [run / "checkpoints" / ".." / "checkpoints" / "step-000000004" / "common.pt", tmp_path / "link" / "x.pt"]
    named = lambda place, suffix: place.with_suffix(suffix) if place.suffix else place / f"x{suffix}"  # noqa: E731
    commands = {
        "export -o": lambda place: ["export", str(trained), "--format", "torchscript", "-o", str(place)],
        "play --video": lambda place: ["play", str(trained), "--video", str(named(place, ".mp4"))],
        "plot -o": lambda place: ["plot", str(trained), "-o", str(place if place.is_dir() else named(place, ".png"))],
    }
    checked = 0
    for option, argv in commands.items():
        for place in places:
            assert main(argv(place)) == 2, (option, place)
            err = capsys.readouterr().err
            assert err.count("\n") == 1 and "a step of a run's storage" in err, (option, place, err)
            checked += 1
    after = {path: path.read_bytes() for path in sorted(run.rglob("*")) if path.is_file()}
    assert after == before, "nothing in the storage written, nothing added"
    print(f"{checked} outputs inside a step refused, the storage untouched")
    assert main(["export", str(trained), "--format", "torchscript", "-o", str(run / "policy.pt")]) == 0  # beside them


@needs_egl
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_play_stopped_part_way_leaves_no_video_cut_short_and_the_one_before_whole(trained, tmp_path, stop) -> None:
    """A probe's Ctrl-C during ``play --video`` left a video of 46 frames, less than one episode, without a word,
    in the place of the one there before. The frames go to a file of their own until every episode is in: stopped
    after its first episode, the play ends with the stop's line and code, and the path holds what it held."""
    video, output = tmp_path / "cheetah.mp4", tmp_path / "output.txt"
    video.write_bytes(b"the video of an earlier play")
    command = [sys.executable, "-m", "ftrain", "play", str(trained), "--episodes", "500", "--video", str(video)]
    with output.open("w") as sink:
        proc = launch(
            command,
            cwd=REPO,
            env=child_env(),
            stdout=sink,
            stderr=subprocess.STDOUT,
            preexec_fn=as_a_terminal_starts_it,
        )
    wait_for(lambda: "episode 1: return" in output.read_text(), "the first episode")
    proc.send_signal(stop)
    assert finish(proc, timeout=60) == 128 + stop, output.read_text()[-2000:]
    said = "ftrain: interrupted (Ctrl-C)" if stop == signal.SIGINT else "ftrain: stopped by SIGTERM"
    assert output.read_text().endswith(f"{said}\n") and "Traceback" not in output.read_text()
    assert video.read_bytes() == b"the video of an earlier play"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["cheetah.mp4", "output.txt"]


def test_a_model_for_other_spaces_is_refused_by_its_observations_and_actions() -> None:
    """A checkpoint of an env whose observations or actions have changed since was refused as tensor shapes
    (``obs_normalizer._mean is [1, 11] ...``): the line names the sizes first, from rsl-rl's own models, with and
    without observation normalisation, for either parameterisation of the action noise, over generated sizes."""
    rng = random.Random(5)
    checked = 0
    for _ in range(24):
        normalized, std_type = rng.choice([True, False]), rng.choice(["scalar", "log"])
        overrides = [f"policy.obs_normalization={str(normalized).lower()}", f"policy.std_type={std_type}"]
        config = load_config(SMOKE, overrides)
        saved, now = (rng.randint(1, 40), rng.randint(1, 8)), (rng.randint(1, 40), rng.randint(1, 8))
        if saved == now:
            continue
        state = build_actor(config, TensorDict({OBS_GROUP: torch.zeros(1, saved[0])}, batch_size=[1]), saved[1])
        model = build_actor(config, TensorDict({OBS_GROUP: torch.zeros(1, now[0])}, batch_size=[1]), now[1])
        with pytest.raises(RuntimeError) as refused:
            model.load_state_dict(state.state_dict())
        line = load_error_line(refused.value)
        said = [f"it takes {saved[0]} observations, the env gives {now[0]}"] if saved[0] != now[0] else []
        said += [f"it gives {saved[1]} actions, the env takes {now[1]}"] if saved[1] != now[1] else []
        assert line.startswith(f"{'; '.join(said)} (") and " in the model built now" in line, (saved, now, line)
        checked += 1
    print(f"{checked} pairs of spaces checked")
    assert checked >= 20
