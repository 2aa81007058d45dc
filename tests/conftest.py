import contextlib
import socket
import subprocess
import sys
import time
import uuid

import boto3
import pytest
import torch

# --- Storage backends: a real S3 API server (moto) on 127.0.0.1, plus local, file:// and memory:// URLs ---

S3_KEY = "ftrain-test-access-key"
S3_SECRET = "ftrain-test-secret-Wq7vT2pL9"
S3_REGION = "us-east-1"
BACKENDS = ("local", "file", "memory", "s3")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def start_moto(port: int, log_path) -> subprocess.Popen:
    """Start moto's S3 server on 127.0.0.1:``port`` and wait until it accepts connections."""
    log = open(log_path, "ab")  # noqa: SIM115 - the server writes to it for its whole life
    proc = subprocess.Popen(
        [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)], stdout=log, stderr=log
    )
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"moto server exited with {proc.returncode}: see {log_path}")
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
            return proc
        time.sleep(0.05)
    proc.kill()
    raise RuntimeError(f"moto server did not listen on port {port} within 30 s: see {log_path}")


def stop(proc: subprocess.Popen) -> None:
    proc.terminate()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory):
    """moto's real S3 API server in a subprocess; yields its endpoint and fake credentials."""
    port = free_port()
    proc = start_moto(port, tmp_path_factory.mktemp("moto") / "moto.log")
    try:
        yield {"endpoint_url": f"http://127.0.0.1:{port}", "key": S3_KEY, "secret": S3_SECRET, "region": S3_REGION}
    finally:
        stop(proc)


def create_bucket(server: dict) -> str:
    bucket = f"ftrain-{uuid.uuid4().hex[:12]}"
    client = boto3.client(
        "s3",
        endpoint_url=server["endpoint_url"],
        aws_access_key_id=server["key"],
        aws_secret_access_key=server["secret"],
        region_name=server["region"],
    )
    client.create_bucket(Bucket=bucket)
    return bucket


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


# --- end of storage fixtures ---


@pytest.fixture(autouse=True)
def stop_leftover_supervisors():
    """A failed test must not leave a supervisor (and its workers) running."""
    yield
    from runs import stop_launched

    stop_launched()


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
