"""Fixtures only: storage backends (a real S3 API server on 127.0.0.1), an etcd server, and clean-up. Helpers live in
helpers.py."""

import shutil
import socket
import subprocess
import uuid

import pytest

from ftrain.tools.outage import S3Server, free_port, start_moto, stop

from helpers import (
    BACKENDS,
    S3_KEY,
    S3_REGION,
    S3_SECRET,
    S3Outage,
    create_bucket,
    make_certificates,
    stop_launched,
    wait_for,
)

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


@pytest.fixture
def etcd_server(tmp_path):
    """A private etcd (v2 API on, as torch's etcd-v2 rendezvous needs) on free ports of 127.0.0.1, its data in
    ``tmp_path``; yields its client address ``HOST:PORT``. Skips where there is no etcd binary."""
    yield from _etcd(tmp_path, "http", [])


@pytest.fixture
def etcd_tls_server(tmp_path):
    """The same over TLS, answering only clients with a certificate of its CA; yields ``(HOST:PORT, certificates)``
    (``helpers.make_certificates``)."""
    certificates = make_certificates(tmp_path)
    options = ["--cert-file", certificates["server"], "--key-file", certificates["server_key"]]
    options += ["--trusted-ca-file", certificates["ca"], "--client-cert-auth"]
    for endpoint in _etcd(tmp_path, "https", options):
        yield endpoint, certificates


def _etcd(tmp_path, scheme: str, options: list):
    binary = shutil.which("etcd")
    if binary is None:
        pytest.skip("no etcd binary: install Debian's etcd-server (launch/setup.sh does, as root)")
    port = free_port()
    client, peer = f"{scheme}://127.0.0.1:{port}", f"http://127.0.0.1:{free_port()}"
    command = [binary, "--enable-v2", "--data-dir", str(tmp_path / "etcd"), "--listen-client-urls", client]
    command += ["--advertise-client-urls", client, "--listen-peer-urls", peer, "--initial-advertise-peer-urls", peer]
    command += ["--initial-cluster", f"default={peer}", *map(str, options)]
    with open(tmp_path / "etcd.log", "ab") as log:
        proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    try:
        wait_for(lambda: _listens(port) or proc.poll() is not None, "etcd", timeout=30, interval=0.1)
        assert proc.poll() is None, (tmp_path / "etcd.log").read_text()
        yield f"127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def _listens(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False


@pytest.fixture(autouse=True)
def stop_leftover_supervisors():
    """A failed test must not leave a supervisor (and its workers) running."""
    yield
    stop_launched()
