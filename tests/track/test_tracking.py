"""W&B (offline) and MLflow (a local SQLite store) fed by real supervised training whose workers are SIGKILLed, then
read back from what the trackers wrote (W&B: its offline transaction logs); an unreachable tracker; bad input."""

from __future__ import annotations

import csv
import json
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from ftrain.config import load_config
from ftrain.errors import UserError
from ftrain.supervise.options import EXIT_DONE
from ftrain.track import sender as sender_module
from ftrain.track.sender import GOES_ON, QUEUE_ROWS, Sender
from ftrain.track.wandb_log import records
from ftrain.train.hooks import CSV_ONLY

from helpers import (
    REPO,
    SMOKE,
    child_env,
    events,
    final_manifest,
    finish,
    free_port,
    launch,
    metrics_by_iteration,
    run_train,
    train_command,
    training,
    wait_for,
)

OFFLINE = {
    "WANDB_MODE": "offline",
    "WANDB_SILENT": "true",
    "WANDB_DISABLE_GIT": "true",
    "WANDB_DISABLE_CODE": "true",
    "WANDB__DISABLE_STATS": "true",  # W&B reads its private settings from WANDB__NAME
    "WANDB_ERROR_REPORTING": "false",
    "MLFLOW_DISABLE_TELEMETRY": "true",
    "DO_NOT_TRACK": "true",
}
"""Nothing of these tests reaches a network: W&B offline, no telemetry."""
SECRET = "tracker-test-secret-8Hq2Zr"
ITERATIONS = 20


def wandb_history(log_dir: Path) -> tuple[set[str], list[dict], list[dict]]:
    """The run ids, history rows (in the order written) and configs of every offline run directory of a run."""
    ids, rows, configs = set(), [], []
    for path in sorted(log_dir.glob("wandb/offline-run-*/run-*.wandb")):
        for record in records(path):
            kind = record.WhichOneof("record_type")
            if kind == "run":
                ids.add(record.run.run_id)
                configs.append({item.key: json.loads(item.value_json) for item in record.run.config.update})
            elif kind == "history":
                rows.append(
                    {"/".join(item.nested_key) or item.key: json.loads(item.value_json) for item in record.history.item}
                )
    return ids, rows, configs


def supervise(storage: Path, *overrides: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "2", "--backoff-initial", "0.2"]
    command += [SMOKE, "--storage", str(storage), "log.console=false", "dist_timeout=10", *overrides]
    output = open(f"{storage}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
    return launch(command, cwd=storage.parent, env=child_env(OFFLINE), stdout=output, stderr=subprocess.STDOUT)


@pytest.mark.slow
def test_one_tracker_run_across_restarts_every_iteration_once_no_secret(tmp_path):
    storage, mlflow_uri = tmp_path / "run", f"sqlite:///{tmp_path / 'mlflow.db'}"
    # MLflow makes a new SQLite store's tables in migrations that a process killed meanwhile leaves half done (the
    # store then fails every later open): the store exists before the run, as a store in use does
    MlflowClient(mlflow_uri).search_experiments()
    proc = supervise(
        storage,
        f"iterations={ITERATIONS}",
        "log.wandb.mode=offline",
        "log.wandb.tags=[ci]",
        f"log.mlflow.tracking_uri={mlflow_uri}",
        f"storage.options={{secret: {SECRET}}}",
    )
    for rank, count in ((1, 1), (0, 2)):  # rank 1 then rank 0 SIGKILLed, each a few iterations past a recovery
        recovered = [event for event in events(storage) if event["event"] == "recovered"]
        start = (recovered[-1]["step"] or 0) if recovered else 0
        os.kill(training(storage / "heartbeat", start + 5, [rank])[rank].pid, signal.SIGKILL)
        wait_for(lambda n=count: len([e for e in events(storage) if e["event"] == "recovered"]) >= n, "a recovery")
    assert finish(proc) == EXIT_DONE
    assert final_manifest(storage)["step"] == ITERATIONS
    restarts = [event for event in events(storage) if event["event"] == "restart"]
    assert len(restarts) == 2

    ids, rows, configs = wandb_history(storage)
    assert len(ids) == 1  # one W&B run, continued by each start (a killed one may have flushed nothing to disk)
    steps = [row["_step"] for row in rows]
    assert steps == list(range(1, ITERATIONS + 1))  # every iteration once, in order, across the three starts
    assert rows[-1]["supervisor/restarts"] == 2 and rows[-1]["world_size"] == 2
    assert configs[-1]["storage"]["options"] == {"secret": "***"}
    assert configs[-1]["ftrain"]["config_hash"] == final_manifest(storage)["config_hash"]
    assert not [path for path in storage.rglob("*") if path.is_file() and SECRET.encode() in path.read_bytes()]

    client = MlflowClient(mlflow_uri)
    experiment = client.get_experiment_by_name("smoke")
    (run,) = client.search_runs([experiment.experiment_id])
    assert run.info.status == "FINISHED" and run.data.tags["ftrain.run_id"] in ids
    csv_rows = metrics_by_iteration(storage)
    for key in ("env_steps", "loss/value", "mean_return"):
        history = client.get_metric_history(run.info.run_id, key)
        assert sorted(metric.step for metric in history) == list(range(1, ITERATIONS + 1)), key
        for metric in history:  # the values of the run that went on (bit for bit, so also those logged before)
            assert _same(metric.value, float(csv_rows[metric.step][key])), (key, metric.step)
    restarted = client.get_metric_history(run.info.run_id, "supervisor/restarts")
    assert max(metric.value for metric in restarted) == 2
    assert run.data.params["storage.options.secret"] == "***"
    assert SECRET not in json.dumps([run.data.params, run.data.tags])
    config = json.loads(
        Path(client.download_artifacts(run.info.run_id, "ftrain/config.json", str(tmp_path))).read_text()
    )
    assert config["storage"]["options"] == {"secret": "***"}


@pytest.mark.waits
@pytest.mark.slow
def test_an_unreachable_tracker_costs_one_warning_never_stops_training_and_gets_every_row_when_back(tmp_path):
    closed = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    start = time.monotonic()
    result = subprocess.run(
        [*train_command(tmp_path / "run"), f"log.mlflow.tracking_uri={closed}"],
        cwd=tmp_path,
        env=child_env(OFFLINE),
        capture_output=True,
        text=True,
        timeout=300,
    )
    took = time.monotonic() - start
    assert result.returncode == 0, result.stderr[-3000:]
    assert final_manifest(tmp_path / "run")["step"] == 8
    warnings = [line for line in (result.stdout + result.stderr).splitlines() if "mlflow:" in line]
    assert len(warnings) == 1 and "did not answer" in warnings[0], warnings
    start = time.monotonic()
    run_train(tmp_path / "plain", env=OFFLINE, cwd=tmp_path)  # the tracker changed nothing that was trained
    plain = time.monotonic() - start
    assert took < plain + 30, f"training took {took:.0f} s with an unreachable tracker, {plain:.0f} s without"
    assert final_manifest(tmp_path / "plain")["state_sha256"] == final_manifest(tmp_path / "run")["state_sha256"]

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"  # the tracker back: the run goes on, its first 8 rows sent from the CSV
    MlflowClient(uri).search_experiments()
    run_train(tmp_path / "run", "iterations=10", f"log.mlflow.tracking_uri={uri}", env=OFFLINE, cwd=tmp_path)
    client = MlflowClient(uri)
    (run,) = client.search_runs([client.get_experiment_by_name("smoke").experiment_id])
    with (tmp_path / "run" / "metrics.csv").open() as file:  # read here, not by read_metrics, which the resend uses
        rows = {int(row["iteration"]): row for row in csv.DictReader(file)}
    assert sorted(rows) == list(range(1, 11)) and "world_size" in rows[1]
    for key in rows[1].keys() - set(CSV_ONLY):  # every metric of every row, as the CSV has it
        logged = {metric.step: metric.value for metric in client.get_metric_history(run.info.run_id, key)}
        expected = {step: float(row[key]) for step, row in rows.items() if row[key]}  # (empty: not measured)
        assert logged.keys() == expected.keys() and all(_same(logged[step], expected[step]) for step in logged), key


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        (["log.wandb.projekt=x"], "unknown config key log.wandb.projekt: did you mean log.wandb.project?"),
        (["log.wandb.mode=sometimes"], "log.wandb.mode='sometimes' is unknown"),
        (["log.mlflow.experiment=x"], "log.mlflow is set but mlflow is not installed: pip install 'ftrain[mlflow]'"),
    ],
)
def test_bad_tracker_input_is_one_line_and_exit_2(tmp_path, overrides, fragment):
    hide = "import sys; sys.modules['mlflow'] = None; from ftrain.cli import main; sys.exit(main())"  # not installed
    command = [sys.executable, "-c", hide, "train", SMOKE, "--storage", str(tmp_path / "run"), *overrides]
    result = subprocess.run(command, cwd=REPO, env=child_env(OFFLINE), capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and fragment in result.stderr, result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "run").exists()


@pytest.mark.parametrize(
    ("command", "module", "key"), [("train", "wandb", "mode"), ("supervise", "mlflow", "experiment")]
)
def test_a_tracker_that_is_installed_but_does_not_import_is_refused_before_training(tmp_path, command, module, key):
    """A broken install (here a package that raises on import, as one built against another protobuf does) passed
    the check of what is installed, and the run trained without its tracker after one warning, exit 0."""
    broken = tmp_path / "site" / module
    broken.mkdir(parents=True)
    (broken / "__init__.py").write_text("raise ImportError('built against another protobuf')\n")
    options = ["--nproc-per-node", "1"] if command == "supervise" else []
    args = [command, *options, SMOKE, "--storage", str(tmp_path / "run"), f"log.{module}.{key}=offline"]
    env = child_env({**OFFLINE, "PYTHONPATH": str(tmp_path / "site")})
    result = subprocess.run([sys.executable, "-m", "ftrain", *args], cwd=REPO, env=env, capture_output=True, text=True)
    said = result.stderr.strip().splitlines()
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    where = re.escape(f"{module}/__init__.py, line 1")  # the error's own line, file and line
    fix = re.escape(f"repair it (pip install --force-reinstall 'ftrain[{module}]'), or unset log.{module}")
    line = rf"ftrain: error: log\.{module} is set but {module} does not import \(ImportError: built against another"
    assert len(said) == 1 and re.fullmatch(rf"{line} protobuf \(.*{where}\)\): {fix}", said[0]), said
    assert not (tmp_path / "run").exists()


def test_a_tracker_is_off_until_one_of_its_keys_is_set(monkeypatch):
    config = load_config(SMOKE)
    assert not config.log.wandb.enabled and not config.log.mlflow.enabled
    assert load_config(SMOKE, ["log.wandb.mode=offline"]).log.wandb.enabled
    monkeypatch.setitem(sys.modules, "wandb", None)  # as if not installed
    with pytest.raises(UserError, match=r"pip install 'ftrain\[wandb\]'"):
        load_config(SMOKE, ["log.wandb.project=p"])


def test_an_mlflow_database_that_cannot_be_written_is_refused_before_training(tmp_path):
    """MLflow retries a sqlite file it cannot open for 100 s, in 25 lines of warnings, and the run then said its
    tracker "did not answer": one line of bad input instead, before anything starts."""
    with pytest.raises(UserError, match=r"^cannot write /proc/m.db \(/proc takes no new file: .*\): pass log.mlflow"):
        load_config(SMOKE, ["log.mlflow.tracking_uri=sqlite:////proc/m.db"])
    assert load_config(SMOKE, [f"log.mlflow.tracking_uri=sqlite:///{tmp_path}/new/m.db"]).log.mlflow.enabled


def test_a_worker_without_a_tracker_never_runs_wandb_and_leaves_nothing_in_tmp(tmp_path):
    """rsl-rl imports wandb; ftrain defers its code to first use: no second of start-up per worker, and none of the
    temporary directories wandb makes on import (removed only at a clean exit, so a killed worker left them)."""
    left = "sum('wandb' in name for name in os.listdir(os.environ['TMPDIR']))"
    probe = (
        f"import os, sys, ftrain.train.trainer; print('wandb.sdk' in sys.modules, {left});"
        f"import wandb.sdk.wandb_run; wandb.init; print('wandb.sdk' in sys.modules, {left});"  # a submodule first
        "os._exit(0)"  # as a forked worker ends
    )
    env = {**child_env(), "TMPDIR": str(tmp_path)}
    command = [sys.executable, "-c", probe]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert result.stdout.split() == ["False", "0", "True", "2"], result.stdout + result.stderr


def _same(logged: float, expected: float) -> bool:
    return (math.isnan(logged) and math.isnan(expected)) or logged == expected


@pytest.mark.slow
def test_a_resize_continues_the_tracker_run_and_a_run_forked_into_another_storage_gets_its_own(tmp_path):
    """MLflow across a resize and a fork; the fork also logs to W&B offline, whose files go where the user's
    ``WANDB_DIR`` says (not to the log directory)."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    run, fork, track = tmp_path / "run", tmp_path / "fork", f"log.mlflow.tracking_uri={uri}"
    step = str(run / "checkpoints" / "step-000000004")
    MlflowClient(uri).search_experiments()  # the store's tables made once, before the runs (see the test above)
    run_train(run, "iterations=4", track, ranks=2, env=OFFLINE, cwd=tmp_path, supervised=True)  # artifacts: ./mlruns
    own_dir = {**OFFLINE, "WANDB_DIR": str(tmp_path / "mine")}  # another storage: a new run; W&B's files in WANDB_DIR
    run_train(fork, "iterations=5", track, "log.wandb.mode=offline", f"resume={step}", env=own_dir, cwd=tmp_path)
    assert wandb_history(tmp_path / "mine")[0] and not (fork / "wandb").exists()
    run_train(run, "iterations=6", track, f"resume={step}", env=OFFLINE, cwd=tmp_path)  # the same run, 1 rank not 2
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("smoke").experiment_id])
    assert len(runs) == 2 and len({found.data.tags["ftrain.run_id"] for found in runs}) == 2
    by_storage = {found.data.tags["ftrain.storage"]: found.info.run_id for found in runs}
    sizes = {metric.step: metric.value for metric in client.get_metric_history(by_storage[str(run)], "world_size")}
    assert sizes == {1: 2.0, 2: 2.0, 3: 2.0, 4: 2.0, 5: 1.0, 6: 1.0}
    assert [metric.step for metric in client.get_metric_history(by_storage[str(fork)], "env_steps")] == [5]


class Stuck:
    """A tracker that does not answer until it is let go."""

    name = "stuck"

    def __init__(self) -> None:
        self.answer = threading.Event()
        self.logged: list[int] = []

    def open(self) -> int:
        self.answer.wait()
        return -1

    def log(self, step: int, values: dict[str, float]) -> None:
        self.logged.append(step)

    def close(self, finished: bool) -> None:
        pass


def test_a_stuck_tracker_never_blocks_sending_and_a_full_queue_is_one_warning():
    tracker, lines = Stuck(), []
    sender = Sender(tracker, lambda last: [], dict, lines.append)
    start = time.perf_counter()
    for step in range(1, QUEUE_ROWS + 501):
        sender.send(step, {"x": float(step)})
    assert time.perf_counter() - start < 1.0
    dropped = f"stuck: it is {QUEUE_ROWS} iterations behind: dropping iterations from {QUEUE_ROWS + 1} on; {GOES_ON}"
    assert lines == [dropped]
    tracker.answer.set()
    sender.close(finished=True)
    assert tracker.logged == list(range(1, QUEUE_ROWS + 1)) and len(lines) == 1


class Slow(Stuck):
    """A tracker that answers, slowly: each row takes ``seconds``."""

    name = "slow"

    def __init__(self, seconds: float) -> None:
        super().__init__()
        self.seconds = seconds
        self.answer.set()

    def log(self, step: int, values: dict[str, float]) -> None:
        time.sleep(self.seconds)
        super().log(step, values)


def test_the_end_waits_for_a_slow_tracker_while_it_takes_rows_and_not_for_one_that_stopped(monkeypatch):
    """A tracker resending a run's rows on a busy machine took longer than the end's wait, which left the rows after
    the first few unsent (the unreachable-tracker test, in a full suite on a slowed machine): the end waits while rows
    go, up to ``CLOSE_AT_MOST``, and gives up ``CLOSE_SECONDS`` after the last one."""
    monkeypatch.setattr(sender_module, "CLOSE_SECONDS", 0.3)
    monkeypatch.setattr(sender_module, "CLOSE_AT_MOST", 3.0)
    for tracker, rows, said in (
        (Slow(0.05), 20, None),  # 1 s in all, 0.3 s holds 6 rows: every row
        (Slow(0.5), 20, "slow: did not answer within 0.3 s of the end: "),  # a row per 0.5 s: stopped by the first wait
        (Slow(0.1), 60, "slow: still sending 3 s after the end: "),  # 6 s in all: stopped by the bound
    ):
        lines: list[str] = []
        sender = Sender(tracker, lambda last: [], dict, lines.append)
        for step in range(1, rows + 1):
            sender.send(step, {"x": float(step)})
        sender.close(finished=True)
        if said is None:
            assert lines == [] and tracker.logged == list(range(1, rows + 1))
            continue
        assert len(lines) == 1 and lines[0].startswith(said) and lines[0].endswith(" iterations not sent"), lines
        unsent = int(lines[0][len(said) :].split()[0])  # the row in flight is neither sent nor queued
        assert unsent + len(tracker.logged) in (rows - 1, rows), (lines, tracker.logged)
        assert len(tracker.logged) < 2 if tracker.seconds == 0.5 else len(tracker.logged) > 10, tracker.logged


class Refusing(Stuck):
    """A tracker whose server refuses the run in a long line that ends with the fix (MLflow 3 on its file store)."""

    name = "refusing"

    def open(self) -> int:
        raise RuntimeError(f"The filesystem tracking backend {'is in maintenance mode ' * 40}set ALLOW=true to opt out")


def test_a_tracker_that_fails_says_so_in_one_line_that_keeps_the_fix_at_the_end_of_a_long_error() -> None:
    lines: list[str] = []
    sender = Sender(Refusing(), lambda last: [], dict, lines.append)
    sender.send(1, {"x": 1.0})
    sender.close(finished=True)
    assert len(lines) == 1 and "\n" not in lines[0], lines
    assert lines[0].startswith("refusing: failed (RuntimeError: The filesystem tracking backend is in maint"), lines
    assert lines[0].endswith(f"mode set ALLOW=true to opt out); {GOES_ON}") and " ... " in lines[0], lines
    assert len(lines[0]) < 700, len(lines[0])


def test_the_supervisors_totals_skip_event_lines_damaged_since() -> None:
    """A line that is not an object, or a count of another type, counts as nothing: the tracker, and W&B with it,
    goes on."""
    from ftrain.track.supervisor_totals import totals

    lines = [
        json.dumps({"event": "restart"}),
        json.dumps({"event": "recovered", "lost": 3, "downtime": 1.5}),
        json.dumps({"event": "recovered", "lost": "5", "downtime": None}),
        "[1, 2]",
        "null",
        '{"event": "recov',
    ]
    assert totals(lines) == {
        "supervisor/restarts": 1,
        "supervisor/resizes": 0,
        "supervisor/iterations_lost": 3,
        "supervisor/downtime": 1.5,
    }


def test_an_mlflow_run_left_without_params_by_a_killed_start_gets_them_from_the_next(tmp_path) -> None:
    """A start killed between making its MLflow run and logging the config as params (its open is slow on a new
    store) left the run without them for good: the next start, which finds the run by its tag, logs those missing."""
    from ftrain.track.mlflow_run import RUN_TAG, MlflowRun
    from ftrain.track.sender import RunInfo
    from ftrain.values import dotted

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(uri)
    experiment = client.create_experiment("smoke")
    client.create_run(experiment, tags={RUN_TAG: "run-1"})  # what the killed start left
    config = load_config(SMOKE, [f"log.mlflow.tracking_uri={uri}"])
    info = RunInfo("run-1", "smoke", config.public_dict(), {"config_hash": "h"}, str(tmp_path))
    tracker = MlflowRun(config.log.mlflow, info)
    assert tracker.open() == -1
    tracker.close(True)
    (run,) = client.search_runs([experiment])
    assert run.data.params == {key: str(value) for key, value in dotted(info.config).items()}
    assert len(run.data.params) > 50, "the whole config"
