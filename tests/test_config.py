"""Config loading, overrides, and the one-line errors for bad input (exit code 2, no traceback)."""

import dataclasses
import math
import os
import random
import re
import shutil
import subprocess
import sys
import typing
from pathlib import Path

import pytest
import yaml

from ftrain.ckpt.lease import TTL_ENV, ttl_from_env
from ftrain.ckpt.storage import Storage
from ftrain.config import ELASTIC_NODES_ENV, Config, for_elastic, for_launch, for_world, load_config, local_directories
from ftrain.errors import UserError
from ftrain.train.lr_schedule import horizon_notice

from helpers import REPO, SMOKE, child_env, make_step

LINEAR = ["algorithm.schedule=linear", "algorithm.schedule_iterations=8"]


def test_overrides_are_typed_and_dotted() -> None:
    config = load_config(SMOKE, ["env.num_envs=8", "policy.hidden_dims=[32,32]", "algorithm.learning_rate=3e-4"])
    assert config.env.num_envs == 8
    assert config.policy.hidden_dims == [32, 32]
    assert config.algorithm.learning_rate == pytest.approx(3e-4)
    assert config.name == "smoke"
    assert config.storage.url == "runs/smoke"
    assert config.log_dir == "runs/smoke"


def test_storage_given_twice_differently_is_refused_and_alike_is_taken() -> None:
    """``--storage A storage.url=B``: which one was meant is not for ftrain to pick; the line names both without
    credentials."""
    with pytest.raises(UserError, match=r"^--storage /tmp/a and storage.url=/tmp/b name two storages: pass one of"):
        load_config(SMOKE, ["storage.url=/tmp/b"], storage="/tmp/a")
    assert load_config(SMOKE, ["storage.url=/tmp/a"], storage="/tmp/a").storage.url == "/tmp/a"
    assert load_config(SMOKE, ["storage.url=/tmp/b"]).storage.url == "/tmp/b"
    for spelling in ("/tmp/a/", "file:///tmp/a", "/tmp/x/../a", ""):  # one storage, spelt otherwise: taken
        assert load_config(SMOKE, [f"storage.url={spelling}"], storage="/tmp/a").storage.url == "/tmp/a", spelling
    with pytest.raises(UserError, match=r"^--storage is empty: pass a directory or a URL, or leave it out"):
        load_config(SMOKE, [], storage="")
    with pytest.raises(UserError) as refused:  # credentials in either: never printed
        load_config(SMOKE, ["storage.url=s3://AKIA1:S3CR3T@b/x"], storage="s3://AKIA1:S3CR3T@b/y")
    assert "S3CR3T" not in str(refused.value) and "AKIA1" not in str(refused.value), str(refused.value)


def test_storage_decides_log_dir() -> None:
    assert load_config(SMOKE, [], storage="s3://bucket/runs/x").log_dir == "runs/smoke/s3/bucket/runs/x"
    secret = load_config(SMOKE, [], storage="s3://AKIA1:S3CR3T@bucket/exp1/").log_dir
    assert secret == "runs/smoke/s3/bucket/exp1"  # two storages, two directories; no credential in a path
    for spelling in ("/tmp/x", "file:///tmp/x", "local:///tmp/x"):  # one storage, one log directory: its own
        assert load_config(SMOKE, [], storage=spelling).log_dir == "/tmp/x", spelling
    assert local_directories(load_config(SMOKE, [], storage="local:///tmp/x")) == {
        "storage": "/tmp/x",
        "log_dir": "/tmp/x",
    }
    sas = "abfs://box@acct.dfs.core.windows.net/x?sv=1&se=2026-12-01&sig=S"  # a SAS token rotates: not in the path
    assert load_config(SMOKE, [], storage=sas).log_dir == "runs/smoke/abfs/box@acct.dfs.core.windows.net/x"
    assert load_config(SMOKE, ["log_dir=elsewhere"], storage="s3://b/x").log_dir == "elsewhere"


def test_training_hash_ignores_run_length_and_storage() -> None:
    base = load_config(SMOKE).training_hash()
    assert load_config(SMOKE, ["iterations=99", "checkpoint.interval=5"], storage="other").training_hash() == base
    assert load_config(SMOKE, ["seed=2"]).training_hash() != base
    assert load_config(SMOKE, ["algorithm.clip_param=0.1"]).training_hash() != base


def test_keys_added_later_change_the_hash_only_when_set() -> None:
    """The smoke config's hash as checkpoints recorded it before policy.std_type and reward.* existed: such runs
    still resume."""
    assert load_config(SMOKE).training_hash() == "50aafdccd16c0f69"
    for override in ("policy.std_type=log", "reward.normalize=true", "reward.clip=5", "shared_memory_all_reduce=false"):
        assert load_config(SMOKE, [override]).training_hash() != "50aafdccd16c0f69"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["iteratons=3"], "did you mean iterations"),
        (["algorithm.learning_rat=1"], "did you mean algorithm.learning_rate"),
        (["iterations=abc"], "must be an integer"),
        (["algorithm.gamma=high"], "must be a number"),
        (["iterations=0"], "iterations=0 must be at least 1"),
        (["env.num_envs=-2"], "env.num_envs=-2 must be at least 1"),
        (
            ["algorithm.schedule=adaptive", "algorithm.schedule_iterations=-1"],
            "algorithm.schedule_iterations=-1 must be 0 or more",
        ),
        (["checkpoint.pinned=[4,-1]"], r"checkpoint.pinned=\[4, -1\] holds -1, which is no step"),
        (["noequals"], "is not key=value"),
        ([".=3"], r"override '\.=3' has an empty part in its key: write it like env\.num_envs=8"),
        (["env..id=x"], r"override 'env\.\.id=x' has an empty part in its key"),
        (["policy.std_type=exp"], "policy.std_type='exp' is unknown: use scalar or log"),
        (["policy.activation=Relu"], r"policy.activation='Relu' is unknown \(did you mean relu\?\): use elu, "),
        (["algorithm.schedule=fixd"], r"algorithm.schedule='fixd' is unknown \(did you mean fixed\?\): use "),
        (["reward.clip=0"], "reward.clip=0.0 must be a positive number"),
        (["algorithm.gamma=1.5"], r"algorithm.gamma=1.5 is out of range: use a discount between 0 and 1"),
        (["algorithm.lam=2"], "algorithm.lam=2.0 is out of range: use a GAE lambda between 0 and 1"),
        (["algorithm.clip_param=-0.2"], "algorithm.clip_param=-0.2 is out of range: use a positive clip range"),
        (["algorithm.learning_rate=0"], "algorithm.learning_rate=0.0 is out of range: use a positive rate"),
        (["algorithm.learning_rate=-1"], "algorithm.learning_rate=-1.0 is out of range"),
        (["algorithm.schedule=adaptive", "algorithm.desired_kl=0"], "algorithm.desired_kl=0.0 is out of range"),
        (["algorithm.learning_rate=inf"], "algorithm.learning_rate=inf is out of range"),
        (["algorithm.max_grad_norm=-1"], "algorithm.max_grad_norm=-1.0 is out of range"),
        (["algorithm.value_loss_coef=-0.5"], "algorithm.value_loss_coef=-0.5 is out of range"),
        (["algorithm.entropy_coef=-0.01"], "algorithm.entropy_coef=-0.01 is out of range"),
        (["policy.init_noise_std=-1"], "policy.init_noise_std=-1.0 is out of range: use a positive action noise"),
        (["policy.obs_clip=-1"], "policy.obs_clip=-1.0 is out of range"),
        (["policy.final_noise_std=2", *LINEAR], "final_noise_std=2.0 is out of range: use 0 .* up to policy.init"),
        (["policy.final_noise_std=0.2"], "policy.final_noise_std needs algorithm.schedule_iterations=N"),
        (["policy.final_noise_std=0.2", *LINEAR, "algorithm.class_name=Distillation", "teacher=runs/t"], "PPO's"),
        (["algorithm.gamma=nan"], "algorithm.gamma=nan is out of range"),
        (["seed=-1"], "seed=-1 is out of range: use a seed from 0 to 4294967295"),
        (["teacher=runs/t"], "teacher=runs/t is for distillation: set algorithm.class_name=Distillation"),
        (["seed=4294967296"], "seed=4294967296 is out of range"),
        (["name=../../elsewhere"], r"name='../../elsewhere' names a directory of runs/ \(runs/<name>\): give one word"),
        (["name=/tmp/x"], "name='/tmp/x' names a directory of runs/"),
        (["name=.."], "name='..' names a directory of runs/"),
        (
            ["eval.seed=4294967295", "eval.episodes=2"],
            "eval.seed=4294967295 is out of range: use a seed from 0 to 4294967294",
        ),
        (["policy.hidden_dims=[]"], r"policy.hidden_dims=\[\] must list one or more layer widths of at least 1"),
        (["policy.hidden_dims=[64, 0]"], r"policy.hidden_dims=\[64, 0\] must list"),
        (["policy.hidden_dims=[-5]"], r"policy.hidden_dims=\[-5\] must list"),
        (["hooks=[{target: 'a:B', every: 0}]"], r"^hooks\[0\].every=0 must be at least 1 \(its hook runs every N "),
        (["hooks=[{target: 'a:B'}, {target: 'a:C', every: -3}]"], r"^hooks\[1\].every=-3 must be at least 1"),
        (["hooks=foo"], r"^hooks='foo' must be a list, e.g. hooks=\[\{target: \.\.\.\}\]$"),
        (
            ["hooks=[nosuch.Hook]"],
            r"^hooks\[0\] must be a mapping of its keys \(target, every, kwargs\), got 'nosuch.Hook'$",
        ),
        (["log.wandb.tags=x"], r"^log.wandb.tags='x' must be a list, e.g. log.wandb.tags=\[a,b\]$"),
        (["checkpoint.pinned=3"], r"^checkpoint.pinned=3 must be a list, e.g. checkpoint.pinned=\[3\]$"),
        (["policy.hidden_dims=5"], r"^policy.hidden_dims=5 must be a list, e.g. policy.hidden_dims=\[5\]$"),
        (["policy.hidden_dims=x"], r"^policy.hidden_dims='x' must be a list, e.g. policy.hidden_dims=\[64,64\]$"),
        (
            ["log.wandb.mode=offline", "log.wandb.project=a/b"],
            r"^log.wandb.project='a/b' is no W&B project name \(/\): set log.wandb.project to at most 128 characters "
            r"without / \\ # \? % :$",
        ),
        (["log.wandb.mode=offline", "name=x#?"], r"^name='x#\?' is no W&B project name \(# \?\): set log.wandb.proj"),
        (["log.wandb.mode=offline", f"log.wandb.project={'p' * 129}"], r"is no W&B project name \(129 characters\)"),
    ],
)
def test_bad_overrides_raise_user_errors(overrides: list[str], message: str) -> None:
    with pytest.raises(UserError, match=message):
        load_config(SMOKE, overrides)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["configs/missing.yaml"], "config file 'configs/missing.yaml' does not exist"),
        ([SMOKE, "iteratons=3"], "unknown config key iteratons: did you mean iterations?"),
        ([SMOKE, "algorithm.learning_rat=3e-4"], "unknown config key algorithm.learning_rat: did you mean algorithm."),
        ([SMOKE, "env.id=NoSuchEnv-v0"], "env.id='NoSuchEnv-v0' is not a registered gymnasium environment"),
        ([SMOKE, "env.id=HalfCheeta-v5"], "did you mean 'HalfCheetah-v5'"),
        ([SMOKE, "env.id="], "env.id='' is not a registered gymnasium environment: use one of Ant-v4, "),
        ([SMOKE, "env.id="], "(an env of your own: env.id=yourmodule:EnvId)"),
        (
            [SMOKE, "env.id=Pendulum-v1"],
            "env.id='Pendulum-v1' is not a MuJoCo environment: ftrain trains environments whose core is a MujocoEnv",
        ),
        ([SMOKE, "env.id=CartPole-v1"], "env.id='CartPole-v1' is not a MuJoCo environment"),
        ([SMOKE, "env.id=BipedalWalker-v3"], "env.id='BipedalWalker-v3' is not a MuJoCo environment"),
        ([SMOKE, "env.id=HalfCheetah-v3"], "env.id='HalfCheetah-v3' is not a MuJoCo environment"),
        ([SMOKE, "iterations=ten"], "iterations='ten' must be an integer, e.g. iterations=300"),
        ([SMOKE, "env.num_envs=0"], "env.num_envs=0 must be at least 1"),
        ([SMOKE, "algorithm.learning_rate=-1"], "algorithm.learning_rate=-1.0 is out of range: use a positive rate"),
        ([SMOKE, "seed=-1"], "seed=-1 is out of range"),
        ([SMOKE, "resume=/nonexistent/run"], "resume=/nonexistent/run: /nonexistent/run does not exist: pass a run's"),
    ],
)
def test_cli_bad_input_is_one_line_exit_2(args: list[str], message: str) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "ftrain", "train", *args], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert lines == [f"ftrain: error: {lines[0].removeprefix('ftrain: error: ')}"], result.stderr
    assert message in lines[0]
    assert "Traceback" not in result.stderr


def test_a_config_file_not_in_utf8_or_with_a_key_given_twice_is_refused_in_one_line(tmp_path) -> None:
    """Plain YAML keeps the last of two equal keys without a word (a merge's keys may be given again); a file in
    another encoding was a UnicodeDecodeError traceback."""
    cases = {
        b"\xff\xfe\x00seed: 1\n": "is not UTF-8 text (byte 0): save it as UTF-8 YAML",
        b"seed: 1\niterations: 3\nseed: 2\n": "at line 3, column 1 (the key 'seed' is given twice)",
        b"env:\n  num_envs: 2\n  num_envs: 4\n": "at line 3, column 3 (the key 'num_envs' is given twice)",
    }
    for number, (text, line) in enumerate(cases.items()):
        config = tmp_path / f"{number}.yaml"
        config.write_bytes(text)
        with pytest.raises(UserError, match=re.escape(line)):
            load_config(str(config))
    merged = tmp_path / "merged.yaml"
    merged.write_text("base: &b {num_envs: 2, kwargs: {}}\nenv:\n  <<: *b\n  num_envs: 4\n")
    with pytest.raises(UserError, match="unknown config key base"):  # read, and the merge's key overridden
        load_config(str(merged))


def test_the_lease_ttl_from_the_environment_must_be_a_number_of_seconds_a_lease_record_takes(monkeypatch) -> None:
    for text in ("abc", "0", "-5", "inf", "nan", "0.0005", "1e12"):
        monkeypatch.setenv(TTL_ENV, text)
        with pytest.raises(UserError, match=f"^{TTL_ENV}='{text}' must be a number of seconds from 0.001 to 1e"):
            ttl_from_env()
    monkeypatch.setenv(TTL_ENV, "12.5")
    assert ttl_from_env() == 12.5


def test_an_empty_config_file_is_refused_unless_overrides_say_what_to_train(tmp_path) -> None:
    empty = tmp_path / "empty.yaml"
    empty.write_text("# to be filled in\n")
    with pytest.raises(UserError, match=r"^config file '.*empty.yaml' is empty: give it keys \(configs/smoke.yaml"):
        load_config(str(empty))
    assert load_config(str(empty), ["env.id=Hopper-v5"]).env.id == "Hopper-v5"  # the defaults, as asked


def test_a_yaml_error_names_the_file_the_line_the_column_and_the_problem(tmp_path) -> None:
    config = tmp_path / "broken.yaml"
    config.write_text("env:\n  num_envs: [4, 8\nseed: 1\n")
    with pytest.raises(UserError) as raised:
        load_config(str(config))
    assert str(raised.value) == (
        f"config file {str(config)!r} is not valid YAML at line 3, column 5 (expected ',' or ']', but got ':'): "
        "fix the syntax"
    )


@pytest.mark.parametrize("path", sorted((REPO / "configs").glob("*.yaml")), ids=lambda path: path.stem)
def test_every_shipped_config_loads_and_none_warns_about_its_learning_rate_horizon(path) -> None:
    config = load_config(str(path))
    assert horizon_notice(config.algorithm, config.iterations) is None  # no config warns about itself


def test_an_iterations_override_scales_a_linear_schedule_to_the_run_and_nothing_else() -> None:
    config = load_config(str(REPO / "configs" / "halfcheetah.yaml"), ["iterations=300"])
    assert config.algorithm.schedule_iterations == 300
    assert horizon_notice(config.algorithm, config.iterations) is None  # the README's command does not warn
    both = load_config(
        str(REPO / "configs" / "halfcheetah.yaml"), ["iterations=300", "algorithm.schedule_iterations=500"]
    )
    assert both.algorithm.schedule_iterations == 500  # the user's horizon stands, and its line says so
    assert "rate ends at" in horizon_notice(both.algorithm, both.iterations)
    adaptive = load_config(SMOKE, ["iterations=3"])  # no linear schedule: what is trained stays the same
    assert adaptive.algorithm.schedule_iterations == 0
    assert adaptive.training_hash() == load_config(SMOKE).training_hash()


def test_total_envs_are_shared_evenly_by_the_ranks_or_refused_in_one_line() -> None:
    config = load_config(SMOKE, ["env.total_envs=12"])
    assert [for_world(config, world).env.num_envs for world in (1, 2, 3, 4, 6)] == [12, 6, 4, 3, 2]
    assert config.training_hash() == for_world(config, 4).training_hash()  # the share per rank is not trained
    assert for_world(load_config(SMOKE), 4).env.num_envs == 4  # without it: env.num_envs per rank, as configured
    with pytest.raises(UserError, match=r"^env.total_envs=12 cannot be shared evenly by 5 ranks: use a multiple of 5"):
        for_world(config, 5)


def test_an_elastic_launch_takes_a_total_only_where_every_world_it_may_resize_to_shares_it() -> None:
    """Generated launches (MIN:MAX nodes of N ranks, as ftrun tells its workers): a total is taken where every world
    from MIN to MAX nodes divides it, else refused at the start, naming the first world that does not; a total counted
    per rank, or a launch that is not elastic, only at its own world."""
    rng = random.Random(52)
    checked = refused = 0
    for _ in range(400):
        least, per_node = rng.randint(1, 4), rng.randint(1, 8)
        most = least + rng.randint(0, 3)
        shared = math.lcm(*(nodes * per_node for nodes in range(least, most + 1)))  # half the totals: a multiple
        total = rng.choice([rng.randint(1, 96), shared * rng.randint(1, 3)])
        environ = {ELASTIC_NODES_ENV: f"{least}:{most}", "LOCAL_WORLD_SIZE": str(per_node)}
        world = rng.randint(least, most) * per_node
        config = load_config(SMOKE, [f"env.total_envs={total}"])
        odd = [nodes * per_node for nodes in range(least, most + 1) if total % (nodes * per_node)]
        if odd:
            first_odd = rf"^env.total_envs={total} cannot be shared evenly by (the )?{odd[0]} "
            with pytest.raises(UserError, match=first_odd):
                for_launch(config, world, environ)
            refused += 1
        else:
            assert for_launch(config, world, environ).env.num_envs * world == total
        assert for_launch(load_config(SMOKE), world, environ).env.num_envs == load_config(SMOKE).env.num_envs
        checked += 1
    assert for_launch(load_config(SMOKE, ["env.total_envs=6"]), 2, {}).env.num_envs == 3  # not elastic: 4 not asked
    print(f"{checked} elastic launches checked, {refused} refused")
    assert 50 < refused < checked - 50


SHIPPED_PPO = ["ant", "halfcheetah", "halfcheetah_large", "hopper", "reach", "walker2d"]


@pytest.mark.parametrize("name", SHIPPED_PPO)
def test_a_shipped_config_trains_one_global_batch_at_every_world_size_that_divides_it(name) -> None:
    """The world size is not a hyperparameter of the shipped configs: they count the run's environments, so 1 rank
    and N ranks roll out the same environments (tests/train/test_world_size.py trains HalfCheetah's at 1, 2, 4 and 8
    ranks against one rank, and every shipped config at 4 and 8); an ``env.num_envs=N`` override counts per rank, as
    its name says, a section's mapping too, and both counts at once are refused."""
    config = load_config(str(REPO / "configs" / f"{name}.yaml"))
    total = config.env.total_envs
    worlds = [world for world in range(1, total + 1) if total % world == 0]
    assert len(worlds) >= 5 and all(for_world(config, world).env.num_envs * world == total for world in worlds)
    per_rank = load_config(str(REPO / "configs" / f"{name}.yaml"), ["env.num_envs=4"])
    assert (per_rank.env.total_envs, for_world(per_rank, 3).env.num_envs) == (0, 4)
    section = load_config(str(REPO / "configs" / f"{name}.yaml"), ["env={num_envs: 4}"])  # a section's keys count
    assert (section.env.total_envs, for_world(section, 3).env.num_envs) == (0, 4)
    for both in (["env.num_envs=4", "env.total_envs=8"], ["env={total_envs: 8}", "env.num_envs=4"]):
        with pytest.raises(UserError, match=r"^env.num_envs=4 \(per rank\) and env.total_envs=8 \(in all\) both"):
            load_config(str(REPO / "configs" / f"{name}.yaml"), both)
    print(f"{name}: env.total_envs={total} shared evenly at {len(worlds)} world sizes {worlds}")


def test_a_storage_or_log_dir_that_cannot_be_made_is_one_line_exit_2(tmp_path) -> None:
    cases = [  # /proc takes no new directories, whoever asks (a read-only mount answers alike, with its own reason)
        (["train", SMOKE, "--storage", "/proc/ftrain-run"], "storage /proc/ftrain-run cannot be made (No such file"),
        (["supervise", SMOKE, "--storage", "/proc/ftrain-run"], "storage /proc/ftrain-run cannot be made"),
        (
            ["train", SMOKE, "--storage", str(tmp_path / "run"), "log_dir=/proc/ftrain-logs"],
            "log_dir /proc/ftrain-logs",
        ),
    ]
    for args, message in cases:
        result = subprocess.run([sys.executable, "-m", "ftrain", *args], cwd=REPO, capture_output=True, text=True)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert result.stderr.count("\n") == 1 and message in result.stderr, result.stderr
        assert result.stderr.endswith("): pass a directory you can write\n"), result.stderr


def test_supervise_refuses_total_envs_its_world_cannot_share_before_it_launches_anything(tmp_path) -> None:
    storage = tmp_path / "run"
    args = ["supervise", "--nproc-per-node", "2", SMOKE, "--storage", str(storage), "env.total_envs=5"]
    result = subprocess.run([sys.executable, "-m", "ftrain", *args], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    refused = "env.total_envs=5 cannot be shared evenly by 2 ranks: use a multiple of 2, a number of ranks that"
    assert result.stderr == f"ftrain: error: {refused} divides 5, or env.num_envs=N to count per rank\n"
    assert not storage.exists() and list(tmp_path.iterdir()) == []  # no storage, no log directory
    elastic = ["--nnodes", "2:4", "--nproc-per-node", "8", "--rdzv-endpoint", "127.0.0.1:9", "configs/ant.yaml"]
    env = {**os.environ, "FTRAIN_RDZV_SECRET": "a" * 32}  # every world from 2 to 4 nodes, before anything starts
    args = ["supervise", *elastic, "--storage", str(storage)]
    result = subprocess.run([sys.executable, "-m", "ftrain", *args], cwd=REPO, env=env, capture_output=True, text=True)
    refused = "env.total_envs=32 cannot be shared evenly by the 24 ranks of 3 nodes (--nnodes 2:4, 8 per node): set a"
    assert result.returncode == 2 and result.stderr.startswith(f"ftrain: error: {refused}"), result.stderr
    assert result.stderr.endswith("(env.total_envs=96), or env.num_envs=N to count per rank\n") and not storage.exists()
    per_rank = load_config(str(REPO / "configs" / "ant.yaml"), ["env.num_envs=4"])
    for_elastic(per_rank, 2, 4, 8)  # counted per rank: every world takes it
    for_elastic(load_config(str(REPO / "configs" / "ant.yaml"), ["env.total_envs=96"]), 2, 4, 8)
    with pytest.raises(UserError, match=r"set a total that every world divides, or env.num_envs=N"):  # lcm 5,765,760
        for_elastic(load_config(str(REPO / "configs" / "ant.yaml")), 2, 16, 8)


@pytest.mark.parametrize("command", ["train", "supervise"])
def test_a_checkpoints_directory_that_takes_no_file_is_one_line_exit_2_before_the_run_starts(tmp_path, command):
    """A run's ``checkpoints/`` that refuses new files (immutable as root, who passes every permission check; read
    and list only otherwise): ``ftrain train`` trained and then held up to an hour retrying its saves, where the
    supervisor refused at once. Both refuse before training, in one line, and leave the run's steps as they were."""
    storage = tmp_path / "run"
    make_step(Storage.open(str(storage)), 2)
    checkpoints = storage / "checkpoints"
    root = os.geteuid() == 0
    if root and (not shutil.which("chattr") or subprocess.run(["chattr", "+i", str(checkpoints)]).returncode):
        pytest.skip("root passes every permission check, and chattr +i is not available here")
    if not root:
        checkpoints.chmod(0o555)
    try:
        words = [sys.executable, "-m", "ftrain", command, SMOKE, "--storage", str(storage), "iterations=4"]
        result = subprocess.run(words, env=child_env(), capture_output=True, text=True)
    finally:
        if root:
            subprocess.run(["chattr", "-i", str(checkpoints)])
        else:
            checkpoints.chmod(0o755)
    why = "Operation not permitted" if root else "Permission denied"
    assert result.returncode == 2 and result.stderr == (
        f"ftrain: error: cannot write {checkpoints} (it takes no new file: {why}): make it writable (its "
        "permissions, its mount), or pass --storage another directory\n"
    ), result.stderr
    assert sorted(os.listdir(storage)) == ["checkpoints"] and os.listdir(checkpoints) == ["step-000000002"]


def test_a_storage_or_log_dir_that_is_a_file_is_one_line_exit_2_and_the_file_is_left_alone(tmp_path) -> None:
    file = tmp_path / "notes.txt"
    file.write_text("not a directory")
    cases = [
        (["train", SMOKE, "--storage", str(file)], f"storage {file} is not a directory: pass a directory path"),
        (["supervise", SMOKE, "--storage", str(file / "run")], f"storage {file / 'run'} is not a directory ({file} is"),
        (["train", SMOKE, "--storage", str(tmp_path / "run"), f"log_dir={file}"], f"log_dir {file} is not a directory"),
        (["ckpt", "ls", str(file)], f"{file} is a file: pass a run's storage (the directory holding checkpoints/)"),
    ]
    for args, message in cases:
        result = subprocess.run([sys.executable, "-m", "ftrain", *args], cwd=REPO, capture_output=True, text=True)
        assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
        assert result.stderr.count("\n") == 1 and message in result.stderr, result.stderr
    assert file.read_text() == "not a directory" and sorted(tmp_path.iterdir()) == [file]


@pytest.mark.parametrize(
    ("typed", "meant"), [("walker2d", "Walker2d-v5"), ("HalfCheetah", "HalfCheetah-v5"), ("hoper-v5", "Hopper-v5")]
)
def test_an_env_id_without_its_version_or_misspelt_is_told_the_one_meant(typed, meant) -> None:
    """A start of several ids (each version of one env) is no reason to name none: difflib picks among them."""
    from ftrain.config import EnvConfig
    from ftrain.train.env_ids import check_env_id

    told = f"env.id={typed!r} is not a registered gymnasium environment: did you mean {meant!r}"
    with pytest.raises(UserError, match=re.escape(told)):
        check_env_id(EnvConfig(id=typed))


def test_a_section_set_whole_by_an_override_merges_a_mapping_and_refuses_anything_else() -> None:
    """Every section of the config at any depth (generated from ``Config``): ``S=null`` replaced what the file set
    there with the defaults without a word; now a value is refused in one line naming the section and one of its keys,
    and a mapping (``S={}``, ``S={key: value}``) merges into the file's section."""

    def sections(kind: type, prefix: str = "") -> list[tuple[str, type]]:
        found = []
        for name, hint in typing.get_type_hints(kind).items():
            if dataclasses.is_dataclass(hint):
                found += [(prefix + name, hint), *sections(hint, f"{prefix}{name}.")]
        return found

    plain = load_config(SMOKE, [])
    checked = 0
    for section, kind in sections(Config):
        for value in ("null", "5", "[1]", "text"):
            with pytest.raises(UserError, match=rf"^override {re.escape(section)}={re.escape(value)}: {section} is a"):
                load_config(SMOKE, [f"{section}={value}"])
            checked += 1
        assert load_config(SMOKE, [f"{section}={{}}"]) == plain, section
        key = dataclasses.fields(kind)[0].name
        here = plain
        for part in [*section.split("."), key]:
            here = getattr(here, part)
        if isinstance(here, (int, float, str)) and not isinstance(here, bool):
            assert load_config(SMOKE, [f"{section}={{{key}: {here!r}}}"]) == plain, section
        checked += 1
    print(f"{checked} overrides of {checked // 5} sections checked")
    assert checked >= 5 * 8
    assert load_config(SMOKE, ["env={num_envs: 8}"]).env.id == plain.env.id  # the file's other keys stay


def test_a_runs_config_yaml_follows_its_directory_only_where_the_whole_run_moved(tmp_path) -> None:
    """A local run's config.yaml read where its directory now lies goes on there when the place it names is gone
    (tests/train/test_training.py trains it, supervised too); a copy whose original is still there, a storage
    elsewhere, a file that lies in no run's directory, or a file read in place is taken as written."""
    old, new, other = tmp_path / "old", tmp_path / "new", tmp_path / "other"

    def saved_in(directory: Path, storage: str, log_dir: str, run: bool = True) -> Config:
        directory.mkdir(exist_ok=True)
        (directory / "storage.txt").unlink(missing_ok=True)
        if run:
            (directory / "storage.txt").write_text("whatever a claim last wrote\n")
        config = {"env": {"id": "HalfCheetah-v5"}, "storage": {"url": storage}, "log_dir": log_dir}
        (directory / "config.yaml").write_text(yaml.safe_dump(config))
        return load_config(str(directory / "config.yaml"))

    for spelt in (str(old), f"file://{old}/", f"{old}/"):  # however the storage was spelt
        moved = saved_in(new, spelt, str(old))
        assert moved.storage.url == moved.log_dir == str(new), spelt
    overridden = load_config(str(new / "config.yaml"), [f"log_dir={other}"])  # the command line wins
    assert (overridden.storage.url, overridden.log_dir) == (str(new), str(other))
    no_run = saved_in(other, str(old), str(old), run=False)  # a file alone, in no run's directory
    assert no_run.storage.url == no_run.log_dir == str(old)
    elsewhere = saved_in(new, str(other), str(old))  # its storage was not its log directory
    assert (elsewhere.storage.url, elsewhere.log_dir) == (str(other), str(old))
    old.mkdir()
    copied = saved_in(new, str(old), str(old))  # the original is still there: the file names it
    assert copied.storage.url == copied.log_dir == str(old)
    in_place = saved_in(old, str(old), str(old))
    assert in_place.storage.url == in_place.log_dir == str(old)


@pytest.mark.slow  # trains
def test_a_path_written_with_a_tilde_is_the_home_directory_for_checkpoints_logs_and_plot(tmp_path) -> None:
    """A quoted ``~`` (or one in a config file) went to fsspec, which expands it, for the checkpoints, and to the log
    directory as a directory named ``~`` under the working one: a run in two places, and ``plot`` found nothing. Now
    every spelling (``--storage``, ``storage.url``, ``log_dir``, ``resume``) is the home directory's, as a shell's."""
    home, elsewhere = tmp_path / "home", tmp_path / "cwd"
    home.mkdir(), elsewhere.mkdir()
    env = child_env({"HOME": str(home)})
    spellings = {
        "storage": ["--storage", "~/one"],
        "storage.url": ["storage.url=~/two"],
        "log_dir": ["--storage", str(home / "three"), "log_dir=~/three-logs"],
    }
    for name, words in spellings.items():
        command = [sys.executable, "-m", "ftrain", "train", SMOKE, *words, "iterations=2", "log.console=false"]
        done = subprocess.run(command, cwd=elsewhere, env=env, capture_output=True, text=True)
        assert done.returncode == 0, (name, done.stderr[-2000:])
        assert "~" not in done.stdout, (name, done.stdout)
    assert not list(elsewhere.iterdir())
    assert {path.name for path in (home / "one").iterdir()} >= {"checkpoints", "metrics.csv", "config.yaml"}
    assert (home / "two" / "metrics.csv").exists() and (home / "three-logs" / "metrics.csv").exists()
    resumed = [sys.executable, "-m", "ftrain", "train", SMOKE, "--storage", "~/four", "resume=~/one", "iterations=3"]
    done = subprocess.run([*resumed, "log.console=false"], cwd=elsewhere, env=env, capture_output=True, text=True)
    assert done.returncode == 0 and f"from step 2 ({home / 'one'})" in done.stdout, done.stdout + done.stderr[-2000:]
    plot = [sys.executable, "-m", "ftrain", "plot", "~/one", "-o", str(tmp_path / "curves.png")]
    assert subprocess.run(plot, cwd=elsewhere, env=env, capture_output=True).returncode == 0
    assert (tmp_path / "curves.png").stat().st_size > 0 and not list(elsewhere.iterdir())


@pytest.mark.parametrize(
    ("given", "saved", "log_dir"),
    [
        ("./run//", "{cwd}/run", "{cwd}/run"),
        ("~/runs/a", "{home}/runs/a", "{home}/runs/a"),
        ("../b/./c", "{parent}/b/c", "{parent}/b/c"),
        ("file:///abs/x", "file:///abs/x", "/abs/x"),  # local: logs where it is
        ("s3://KEY:SECRET@bucket/x", "s3://bucket/x", "{cwd}/runs/run/s3/bucket/x"),  # runs/<name>/...
    ],
)
def test_a_runs_saved_config_names_its_local_paths_absolute(tmp_path, monkeypatch, given, saved, log_dir) -> None:
    """``config.yaml`` continues the run from any directory: the storage, the log directory and the teacher that a
    relative path named from the run's working directory are absolute in it, a URL stays as it is (without its
    credentials), ``resume`` stays as typed (the run's manifests name their origin so), and ``allow_config_change``
    is left out: it let one start through, and a later start from the file, edited since maybe, must ask again."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    paths = {"cwd": tmp_path, "home": tmp_path / "home", "parent": tmp_path.parent}
    overrides = [
        f"teacher={given}",
        "algorithm.class_name=Distillation",
        "resume=../r/step-4",
        "allow_config_change=true",
    ]
    config = load_config(None, overrides, given)
    data = config.saved_dict()
    expected = saved.format(**paths)
    assert (data["storage"]["url"], data["teacher"], data["resume"]) == (expected, expected, "../r/step-4")
    assert config.allow_config_change and data["allow_config_change"] is False
    assert data["log_dir"] == log_dir.format(**paths)
