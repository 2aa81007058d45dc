"""The commands that read a storage, as a person runs them: against a real S3 API server with the credentials only in
``--storage-option``, and on a run whose newest save was cut short before its manifest."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ftrain.ckpt.format import MANIFEST, step_dir
from ftrain.ckpt.storage import Storage
from ftrain.config import storage_options

from helpers import REPO, S3_SECRET, SMOKE, child_env, create_bucket, flip_byte, run_train

pytestmark = pytest.mark.slow


def ftrain(*args: str, env: dict | None = None, cwd: Path = REPO) -> subprocess.CompletedProcess:
    """``ftrain ARGS`` with no ``AWS_*`` variable in its environment but those of ``env``."""
    clean = {name: value for name, value in child_env(env).items() if not name.startswith("AWS_")}
    clean |= {name: value for name, value in (env or {}).items() if name.startswith("AWS_")}
    return subprocess.run(
        [sys.executable, "-m", "ftrain", *args], cwd=cwd, env=clean, capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def s3_run(s3_server, tmp_path_factory) -> tuple[str, list[str], Path]:
    """A trained smoke run on S3 (4 iterations, saved at 2 and 4): its URL, the storage options that reach it, and
    the directory it ran in (its logs are in runs/smoke/s3/<bucket>/run there)."""
    url = f"s3://{create_bucket(s3_server)}/run"
    options = [
        *("--storage-option", f"endpoint_url={s3_server['endpoint_url']}"),
        *("--storage-option", f"key={s3_server['key']}"),
        *("--storage-option", f"secret={s3_server['secret']}"),
    ]
    cwd = tmp_path_factory.mktemp("s3-run")
    result = ftrain("train", SMOKE, "--storage", url, *options, "iterations=4", cwd=cwd)
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"[ftrain] saved step 4 to {url}/{step_dir(4)} (" in result.stdout
    play = f"[ftrain] play it: ftrain play {url}   export it: ftrain export {url} --format onnx   (with the storage "
    assert play in result.stdout
    assert S3_SECRET not in result.stdout + result.stderr
    return url, options, cwd


def test_ckpt_play_and_export_read_s3_with_credentials_only_in_storage_options(s3_run, tmp_path) -> None:
    url, options, _ = s3_run
    listed = ftrain("ckpt", "ls", url, *options)
    assert listed.returncode == 0, listed.stderr
    assert [line.split()[:2] for line in listed.stdout.splitlines()[1:3]] == [["4", "committed"], ["2", "committed"]]
    assert listed.stdout.splitlines()[1].endswith("newest, best")
    verified = ftrain("ckpt", "verify", url, *options)
    assert verified.returncode == 0 and verified.stdout.splitlines()[-1] == "2 of 2 committed steps verified"
    shown = ftrain("ckpt", "show", f"{url}/{step_dir(2)}", *options)
    assert shown.returncode == 0 and "step: 2" in shown.stdout
    played = ftrain("play", url, "--episodes", "1", *options)
    assert played.returncode == 0, played.stderr
    assert "mean return over 1 episode:" in played.stdout
    exported = ftrain("export", url, "--format", "onnx", "-o", str(tmp_path / "p.onnx"), *options)
    assert exported.returncode == 0, exported.stderr
    assert "its actions match the actor's" in exported.stdout and (tmp_path / "p.onnx").stat().st_size > 0
    everything = "".join(r.stdout + r.stderr for r in (listed, verified, shown, played, exported))
    assert S3_SECRET not in everything


def test_s3_without_credentials_or_with_a_bad_option_is_one_line(s3_run, s3_server) -> None:
    url, options, _ = s3_run
    endpoint_only = ftrain("ckpt", "ls", url, env={"AWS_ENDPOINT_URL": s3_server["endpoint_url"]})
    assert endpoint_only.returncode == 2
    assert endpoint_only.stderr == (
        f"ftrain: error: no credentials for {url} (endpoint {s3_server['endpoint_url']}): set AWS_ACCESS_KEY_ID and "
        "AWS_SECRET_ACCESS_KEY, or the storage options key and secret (--storage-option key=... --storage-option "
        "secret=..., storage.options in a config)\n"
    )
    malformed = ftrain("ckpt", "verify", url, *options, "--storage-option", "a-secret-without-a-key")
    assert malformed.returncode == 2 and "Traceback" not in malformed.stderr
    assert malformed.stderr.count("\n") == 1 and "a-secret-without-a-key" not in malformed.stderr
    assert "--storage-option number 4 is not KEY=VALUE" in malformed.stderr


def test_verify_tells_a_save_cut_short_from_a_committed_step_that_does_not_verify(tmp_path) -> None:
    """A real run's newest step loses its manifest (what a kill between the shards and the commit leaves): verify
    names it incomplete with its age and passes; a flipped byte in a committed step fails it."""
    storage = tmp_path / "run"
    trained = run_train(storage, "iterations=6", "log.console=true")
    notice = "[ftrain] no episode has finished yet: return and len show rank 0's episodes under way (~) until one has"
    assert notice in trained.stdout
    assert re.search(r"^it 1/6 \| .* \| return ~-?\d+\.\d\d \| len ~\d+ \|", trained.stdout, re.MULTILINE), (
        trained.stdout
    )
    assert trained.stdout.count("no episode has finished yet") == 1
    assert f"[ftrain] run saved in {storage}: newest step 6; logs in {storage}" in trained.stdout
    assert f"[ftrain] play it: ftrain play {storage}   export it: ftrain export {storage} --format onnx" in (
        trained.stdout
    )
    os.remove(storage / step_dir(6) / MANIFEST)
    result = ftrain("ckpt", "verify", str(storage))
    assert result.returncode == 0, result.stdout
    lines = result.stdout.splitlines()
    assert lines[0].startswith("step 6: incomplete (never committed: no manifest; last written ")
    assert (
        lines[0].endswith(" s ago)") and lines[-1] == "2 of 2 committed steps verified; 1 incomplete (never committed)"
    )

    flip_byte(storage / step_dir(4) / "rank-00000.pt")
    failed = ftrain("ckpt", "verify", str(storage))
    assert failed.returncode == 1
    assert "step 4: FAILED" in failed.stdout and "rank-00000.pt: sha256 mismatch" in failed.stdout

    done = run_train(storage, "iterations=2", "log.console=true")  # resumes from step 2: 4 is corrupt, 6 incomplete
    assert "nothing to train: the run is already at step 2, asked for iterations=2 (pass iterations=N" in done.stdout
    assert "iterations: 6\n" in (storage / "config.yaml").read_text()  # the trained run's, not the idle start's


def test_plot_reads_a_log_directory_on_s3(s3_run, tmp_path) -> None:
    url, options, cwd = s3_run
    logs = url.replace("/run", "/logs")
    storage = Storage.open(logs, storage_options(options[1::2]))
    local_logs = cwd / "runs" / "smoke" / "s3" / url.removeprefix("s3://")  # the default for a remote storage
    storage.write_replace("metrics.csv", (local_logs / "metrics.csv").read_bytes())
    plotted = ftrain("plot", logs, "-o", str(tmp_path / "curves.png"), *options)
    assert plotted.returncode == 0, plotted.stderr
    assert plotted.stdout == f"wrote {tmp_path / 'curves.png'}\n" and (tmp_path / "curves.png").stat().st_size > 0
    # the run's own URL: its logs stay on the machine that trained it, found there, named elsewhere
    local_logs = Path("runs") / "smoke" / "s3" / url.removeprefix("s3://")
    here = ftrain("plot", url, "-o", str(tmp_path / "here.png"), *options, cwd=cwd)
    assert here.returncode == 0 and here.stderr == f"ftrain plot: the logs of {url} are in {local_logs}\n", here.stderr
    elsewhere = ftrain("plot", url, "-o", str(tmp_path / "elsewhere.png"), *options, cwd=tmp_path)
    assert elsewhere.returncode == 2 and elsewhere.stderr == (
        f"ftrain: error: {url}/metrics.csv does not exist: a run on this storage logs to "
        f"runs/<name>/s3/{url.removeprefix('s3://')} under the directory it was started in, on the machine that "
        "trained it: pass that directory\n"
    ), elsewhere.stderr
