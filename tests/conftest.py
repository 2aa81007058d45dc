"""Fixtures only: storage backends (a real S3 API server on 127.0.0.1), an etcd server, and clean-up. Helpers live in
helpers.py."""

import contextlib
import fcntl
import os
import resource
import shutil
import signal
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from filelock import FileLock

from ftrain import procfs
from ftrain.identity import ENV_NAMES

import etcd_server as etcd_tools
from helpers import (
    AZURITE_MISSING,
    BACKENDS,
    S3_KEY,
    S3_REGION,
    S3_SECRET,
    S3Outage,
    azurite_blob,
    create_bucket,
    final_manifest,
    make_certificates,
    run_train,
    start_azurite,
    start_fake_gcs,
    stop_launched,
)
from s3_outage import S3Server, free_port, start_moto, stop

os.environ.setdefault("GCSFS_EXPERIMENTAL_ZB_HNS_SUPPORT", "false")
"""gcsfs (2025.10 on) probes each bucket over gRPC for a zonal layout, by default: an emulator has no gRPC endpoint,
and each probe would wait a minute. Set before gcsfs is imported, here and in every child (``gcs_server``)."""

# The tests of Ctrl-C start their processes as a terminal's foreground job does, with SIGINT's default action. A process
# started with SIGINT ignored keeps it ignored (ftrain.errors.stop_signals), as the shell asks of a background job, so
# a suite started as one (nohup, `&` in a script) restores it for the processes it starts; the tests of a background
# job start theirs with helpers.AS_A_BACKGROUND_JOB.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

# --- Lanes: the fast lane (-m "not slow") has no servers and no multi-process runs ---

SERVERS = frozenset(
    {"s3_server", "s3_url", "s3_env", "s3_outage", "azurite_server", "gcs_server", "etcd_server", "etcd_tls_server"}
    | {"slurm"}
)
"""Fixtures that start a server (moto's S3, Azurite, fake-gcs-server, etcd, a private SLURM cluster): a test that uses
one is slow."""
LANES_OF_THEIR_OWN = ("cluster", "slurm", "scale")


LONGEST_FIRST = (
    "test_readme.py",
    "cluster/test_slurm.py",
    "train/test_world_size.py",
    "train/test_resume.py",
    "supervise/test_elastic.py",
    "supervise/test_supervisor.py",
    "train/test_user_env.py",
    "cluster/test_netns.py",
    "supervise/test_outages.py",
    "supervise/test_one_run.py",
    "train/test_training.py",
    "train/test_stop_codes.py",
    "comm/test_host_first.py",
    "train/test_distillation.py",
    "ckpt/test_one_history.py",
)
"""The files that take longest (their wall time in ``FTRAIN_TEST_CPU_LOG``), run first: xdist hands out a file at a
time, and a long file taken last keeps one worker busy while the others have nothing left to do."""


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Order the files longest first (``LONGEST_FIRST``, the rest as collected; each file's tests stay together and in
    order), and mark ``slow`` what the fast lane must not run, whatever its file says: a test that starts a server
    (or runs on a backend parametrized as ``"s3"``), and every test of the cluster, SLURM and scale lanes."""

    def rank(item: pytest.Item) -> int:
        path = item.path.as_posix()
        return next((n for n, name in enumerate(LONGEST_FIRST) if path.endswith(f"tests/{name}")), len(LONGEST_FIRST))

    items.sort(key=rank)  # stable: the rest keep their order
    for item in items:
        params = getattr(item, "callspec", None)
        on_s3 = params is not None and any(value == "s3" for value in params.params.values() if isinstance(value, str))
        servers = SERVERS.intersection(getattr(item, "fixturenames", ()))
        if servers or on_s3 or any(item.get_closest_marker(lane) for lane in LANES_OF_THEIR_OWN):
            item.add_marker(pytest.mark.slow)


CPU_LOG = os.environ.get("FTRAIN_TEST_CPU_LOG")
"""A file that gets a line per test: CPU seconds (the test's process and every process it waited for, torchrun's
workers included), wall seconds, test id, xdist worker, start (Unix time). The suite is CPU-bound on two cores:
``--durations`` shows what waits, this what to cut."""
CPU_SLOTS = int(os.environ.get("FTRAIN_TEST_CPU_SLOTS") or os.cpu_count() or 1)
"""How many tests run at once across the xdist workers, one per core: more only slow each other down (measured: three
files at once on two cores took 34.6 min against 30.5, with 24% more CPU time). The SLURM lane's tests take no slot:
they wait for slurmctld (its checks every 30 s) nearly all the time, so launch/test.sh starts one worker more than
the slots, and that lane runs beside the others instead of in the place of one. So do the tests marked ``waits`` (a
lease's expiry, a hang's timeout: under a third of their time on the CPU), in one worker more."""


FREE = ("slurm", "waits")
"""The markers of tests that take no CPU slot."""


TEST_PROCESSES_ENV = "FTRAIN_TEST_PROCESSES"
"""Set in a test worker while a test's body runs, and so in the environment of every process the body starts (and
theirs): what finds them once the test is over. A bare ``os.fork`` of the worker itself is not found (a process's
environment in /proc is the one it was started with)."""
PROCESS_TOKEN = pytest.StashKey[str]()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """Give the processes of the test's body a token of this test (``TEST_PROCESSES_ENV``)."""
    os.environ[TEST_PROCESSES_ENV] = item.stash[PROCESS_TOKEN] = uuid.uuid4().hex
    try:
        yield
    finally:
        os.environ.pop(TEST_PROCESSES_ENV, None)


@pytest.hookimpl(hookwrapper=True)
def pytest_fixture_setup(fixturedef: pytest.FixtureDef, request: pytest.FixtureRequest):
    """A fixture that a test's body sets up (``request.getfixturevalue``: a server) owns its processes: they do not
    get the test's token, and its own teardown stops them."""
    token = os.environ.pop(TEST_PROCESSES_ENV, None)
    try:
        yield
    finally:
        if token is not None:
            os.environ[TEST_PROCESSES_ENV] = token


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None):
    """No process a test's body started outlives the test: one that fails on a timeout (a run that did not stop, a
    supervisor that did not exit) left its processes training beside the tests after it, which then ran at half speed
    (a whole suite 1.5x as long). After the fixtures' own teardown (``stop_leftover_supervisors`` asks supervisors to
    stop), whatever still carries the test's token is SIGKILLed and named in the test's report."""
    yield
    token = item.stash.get(PROCESS_TOKEN, None)
    if token is None:
        return
    killed, alive = kill_processes_of(token)
    if killed:
        item.add_report_section("teardown", "processes", f"left running by the test, SIGKILLed: {killed}")
    if alive:
        item.add_report_section("teardown", "processes", f"still alive 10 s after SIGKILL: {alive}")


def kill_processes_of(token: str, timeout: float = 10.0) -> tuple[list[int], list[int]]:
    """SIGKILL every live process whose environment holds ``token`` until none is left or ``timeout`` passed: the
    pids killed, and those still alive then (asleep in the kernel, e.g. on a hung FUSE mount)."""
    killed: set[int] = set()
    deadline = time.monotonic() + timeout
    while (left := set(procfs.with_environment(TEST_PROCESSES_ENV, token))) and time.monotonic() < deadline:
        for pid in left:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        killed |= left
        time.sleep(0.05)
    return sorted(killed - left), sorted(left)


@pytest.hookimpl(hookwrapper=True, tryfirst=True)  # outermost: the wait for a slot is not the test's (its timeout)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None):
    with cpu_slot(item):
        usage = lambda: sum(  # noqa: E731
            getattr(resource.getrusage(who), field)
            for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
            for field in ("ru_utime", "ru_stime")
        )
        cpu, wall, start = usage(), time.monotonic(), time.time()
        yield
        if CPU_LOG:
            worker = os.environ.get("PYTEST_XDIST_WORKER", "-")
            with open(CPU_LOG, "a") as log:
                log.write(f"{usage() - cpu:.1f} {time.monotonic() - wall:.1f} {item.nodeid} {worker} {start:.0f}\n")


@contextlib.contextmanager
def cpu_slot(item: pytest.Item) -> Iterator[None]:
    """Hold one of ``CPU_SLOTS`` slots (an exclusive ``flock`` of a file in the xdist workers' shared temporary
    directory) while the test runs; none is needed by a SLURM test, one marked ``waits``, or where the workers are no
    more than the slots. Waiters queue (a worker looks for a free slot only while it holds the queue's lock), so that
    a worker that has just freed a slot cannot take it again at once, test after test, while another waits."""
    if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) <= CPU_SLOTS or any(map(item.get_closest_marker, FREE)):
        yield
        return
    shared = Path(item.config.option.basetemp).parent  # xdist gives each worker a directory of the run's
    slots = [shared / f"cpu-slot-{n}" for n in range(CPU_SLOTS)]
    with _flock(shared / "cpu-queue"):
        while (slot := next((fd for fd in map(_try_flock, slots) if fd is not None), None)) is None:
            time.sleep(0.05)
    try:
        yield
    finally:
        os.close(slot)


def _try_flock(path: Path) -> int | None:
    """An open descriptor holding an exclusive ``flock`` of ``path``, None if another process holds one."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


@contextlib.contextmanager
def _flock(path: Path) -> Iterator[None]:
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


# --- Storage backends: a real S3 API server (moto) on 127.0.0.1, plus local, file:// and memory:// URLs ---


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory):
    """moto's real S3 API server in a subprocess; yields its endpoint and fake credentials."""
    port = free_port()
    proc = start_moto(port, tmp_path_factory.mktemp("moto") / "moto.log")
    try:
        yield {"endpoint_url": f"http://127.0.0.1:{port}", "key": S3_KEY, "secret": S3_SECRET, "region": S3_REGION}
    finally:
        stop(proc)


@pytest.fixture
def s3_url(s3_server):
    """``(url, options)`` of a run's storage in a fresh bucket; options carry the endpoint and credentials."""
    options = {"endpoint_url": s3_server["endpoint_url"], "key": s3_server["key"], "secret": s3_server["secret"]}
    return f"s3://{create_bucket(s3_server)}/run", options


@pytest.fixture(scope="session")
def s3_env(s3_server):
    """The same endpoint and credentials as environment variables, for subprocesses (merge into os.environ)."""
    return {
        "AWS_ENDPOINT_URL": s3_server["endpoint_url"],
        "AWS_ACCESS_KEY_ID": s3_server["key"],
        "AWS_SECRET_ACCESS_KEY": s3_server["secret"],
        "AWS_DEFAULT_REGION": s3_server["region"],
    }


@pytest.fixture
def s3_outage(tmp_path):
    """A fresh bucket on an S3 server of the test's own (so that pausing it harms no other test), behind a proxy
    the test switches: see helpers.S3Outage. The server is continued and stopped at the end, whatever happened."""
    server = S3Server(tmp_path / "moto.log")
    try:
        info = {"endpoint_url": server.direct_url, "key": S3_KEY, "secret": S3_SECRET, "region": S3_REGION}
        yield S3Outage(server, f"s3://{create_bucket(info)}/run")
    finally:
        server.stop()


@pytest.fixture(scope="session")
def azurite_server(tmp_path_factory):
    """Azurite's real Azure Blob service in a subprocess, on a free port, with an account and key of its own
    (helpers.start_azurite); yields ``{"connection_string", "key", "port"}``. Skips without Azurite or adlfs."""
    pytest.importorskip("adlfs", reason="adlfs is not installed (pip install -e '.[azure]')")
    command = azurite_blob()
    if command is None:
        pytest.skip(AZURITE_MISSING)
    proc, server = start_azurite(command, free_port(), tmp_path_factory.mktemp("azurite"))
    try:
        yield server
    finally:
        stop(proc)


@pytest.fixture(scope="session")
def gcs_server(tmp_path_factory):
    """fake-gcs-server's real GCS JSON API in a subprocess, on a free port (helpers.start_fake_gcs); yields
    ``{"endpoint_url", "port"}``. gcsfs is told not to probe buckets over gRPC for a zonal layout (an emulator has no
    gRPC endpoint: each probe would wait a minute); its plain JSON API is what ftrain uses."""
    pytest.importorskip("gcsfs", reason="gcsfs is not installed (pip install -e '.[gcs]')")
    proc, server = start_fake_gcs(free_port(), tmp_path_factory.mktemp("fake-gcs"))
    try:
        yield server
    finally:
        stop(proc)


@pytest.fixture(params=BACKENDS)
def storage_url(request, tmp_path, monkeypatch):
    """``(url, options)`` of an empty run storage on each backend: a relative local path, file://, memory://, s3://."""
    if request.param == "local":
        monkeypatch.chdir(tmp_path)
        return "runs/hc", None
    if request.param == "file":
        return (tmp_path / "run").as_uri(), None
    if request.param == "memory":
        return f"memory://ftrain-test/{uuid.uuid4().hex}", None
    return request.getfixturevalue("s3_url")


@pytest.fixture(scope="session")
def reference_run(tmp_path_factory) -> Callable[[int], Path]:
    """``reference_run(iterations)``: the storage (and log directory) of an uninterrupted 2-rank run of
    configs/smoke.yaml (torchrun, cold workers) of that many iterations, trained once per test run, whatever the
    number of xdist workers (the first to ask trains it under a lock in their shared temporary directory, the others
    wait and read it); read it, never write to it. Faults, supervision, SLURM, warm workers, hooks, the storage and
    the checkpoint schedule change nothing that is trained, so every such run compares with it."""
    shared = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        shared = shared.parent  # each worker's basetemp is a directory of the run's

    def run(iterations: int) -> Path:
        root = shared / f"reference-{iterations}"
        with FileLock(f"{root}.lock"):
            if not (root / "done").exists():
                shutil.rmtree(root, ignore_errors=True)  # a worker that failed halfway
                run_train(root / "run", f"iterations={iterations}", ranks=2)
                (root / "done").touch()
        return root / "run"

    return run


@pytest.fixture(scope="session")
def reference_state(reference_run) -> Callable[[int], str]:
    """``reference_state(iterations)``: the final ``state_sha256`` of ``reference_run(iterations)``."""
    return lambda iterations: final_manifest(reference_run(iterations))["state_sha256"]


@pytest.fixture
def etcd_server(tmp_path):
    """A private etcd (v2 API on, as torch's etcd-v2 rendezvous needs) on free ports of 127.0.0.1, its data in
    ``tmp_path``; yields its client address ``HOST:PORT``. Skips where there is no etcd binary."""
    _skip_without_etcd()
    with etcd_tools.etcd_server(tmp_path) as endpoint:
        yield endpoint


@pytest.fixture
def etcd_tls_server(tmp_path):
    """The same over TLS, answering only clients with a certificate of its CA; yields ``(HOST:PORT, certificates)``
    (``helpers.make_certificates``)."""
    _skip_without_etcd()
    certificates = make_certificates(tmp_path)
    with etcd_tools.etcd_server(tmp_path, certificates) as endpoint:
        yield endpoint, certificates


def _skip_without_etcd() -> None:
    if shutil.which("etcd") is None:
        pytest.skip(etcd_tools.MISSING)


@pytest.fixture(autouse=True)
def own_run_names(monkeypatch):
    """A lease held in this process (``Lease.hold``) names the run in its environment, which every process a test
    starts later inherits, and would join that run: each test's names go with it."""
    for name in ENV_NAMES:
        monkeypatch.setenv(name, "")
        monkeypatch.delenv(name)


@pytest.fixture(autouse=True)
def stop_leftover_supervisors():
    """A failed test must not leave a supervisor (and its workers) running."""
    yield
    stop_launched()
