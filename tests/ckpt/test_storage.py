import contextlib
import errno
import http.server
import json
import logging
import os
import random
import re
import shlex
import socket
import subprocess
import sys
import textwrap
import threading
import time
from urllib.parse import quote, urlsplit

import pytest

from ftrain.ckpt.retry import Backoff
from ftrain.ckpt.storage import Storage, StorageError, StorageUnavailable
from ftrain.errors import EXIT_STORAGE_DOWN, EXIT_USAGE, UserError
from ftrain.redact import display_url

from helpers import REPO, S3_KEY, S3_SECRET, child_env, create_bucket, free_port, train_command


def test_round_trip(storage_url):
    url, options = storage_url
    storage = Storage.open(url, options)
    storage.write_exclusive("checkpoints/step-1/a.pt", b"alpha")
    storage.write_exclusive("checkpoints/step-2/b.pt", b"beta!")
    assert storage.read("checkpoints/step-1/a.pt") == b"alpha"
    assert storage.exists("checkpoints/step-1/a.pt")
    assert not storage.exists("checkpoints/step-1/zzz")
    assert storage.size("checkpoints/step-2/b.pt") == 5
    assert storage.list_dirs("checkpoints") == ["step-1", "step-2"]
    assert storage.list_dirs("nothing/here") == []
    assert storage.list_files("checkpoints/step-2") == {"b.pt": 5}

    storage.write_replace("checkpoints/step-1/marker", b"one")
    storage.write_replace("checkpoints/step-1/marker", b"two")
    assert storage.read("checkpoints/step-1/marker") == b"two"

    storage.delete("checkpoints/step-1/a.pt")
    storage.delete("checkpoints/step-1/a.pt")  # already gone: no error
    assert storage.list_files("checkpoints/step-1") == {"marker": 3}
    storage.delete_tree("checkpoints/step-1")
    storage.delete_tree("checkpoints/step-1")
    assert storage.list_dirs("checkpoints") == ["step-2"]

    with pytest.raises(FileNotFoundError, match=r"a.pt"):
        storage.read("checkpoints/step-1/a.pt")


def test_exclusive_create_refuses_overwrite(storage_url):
    url, options = storage_url
    storage = Storage.open(url, options)
    storage.write_exclusive("d/MANIFEST.json", b"first")
    with pytest.raises(FileExistsError, match=r"MANIFEST.json"):
        storage.write_exclusive("d/MANIFEST.json", b"second")
    assert storage.read("d/MANIFEST.json") == b"first"


def test_a_new_storage_sees_what_another_wrote(storage_url):
    """No stale listings: a second handle (another rank, a later process) lists what the first just wrote."""
    url, options = storage_url
    first, second = Storage.open(url, options), Storage.open(url, options)
    assert second.list_dirs("checkpoints") == []
    first.write_exclusive("checkpoints/step-5/x", b"x")
    assert second.list_dirs("checkpoints") == ["step-5"]
    assert second.list_files("checkpoints/step-5") == {"x": 1}


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("", "empty"),
        ("nosuchproto://x/y", "unknown protocol 'nosuchproto'; use a local path, file://, s3://, gs:// or abfs://"),
        ("1x://a", "malformed"),
        ("s3:/bucket/run", "looks like a mistyped s3:// URL: write s3://bucket/run, or ./s3:/bucket/run for a local"),
        ("s3//bucket/run", "looks like a mistyped s3:// URL: write s3://bucket/run,"),
        ("gs:bucket", "looks like a mistyped gs:// URL: write gs://bucket,"),
        (
            "s3://bucket//run",
            "has an empty, . or .. part in its path, which object stores keep as written: write s3://bucket/run",
        ),
        ("s3://bucket/run/.", "write s3://bucket/run"),
        ("gs://bucket/a/../run/", "write gs://bucket/run"),
    ],
)
def test_bad_url_is_a_user_error(url, message, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(UserError, match=re.escape(message)):
        Storage.open(url)
    assert list(tmp_path.iterdir()) == []  # nothing made in the working directory


def test_s3_without_bucket_or_with_a_missing_one(s3_url):
    _, options = s3_url
    with pytest.raises(UserError, match="names no bucket"):
        Storage.open("s3://", options)
    with pytest.raises(UserError, match="'no-such-bucket' does not exist"):
        Storage.open("s3://no-such-bucket/run", options)


def test_s3_credentials_from_environment(s3_url, s3_env, monkeypatch):
    url, _ = s3_url
    for name, value in s3_env.items():
        monkeypatch.setenv(name, value)
    storage = Storage.open(url)
    storage.write_exclusive("x", b"1")
    assert storage.read("x") == b"1"


def test_s3_missing_credentials(s3_url, tmp_path, monkeypatch):
    url, options = s3_url
    for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_SESSION_TOKEN", "AWS_PROFILE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("AWS_SHARED_CREDENTIALS_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_CONFIG_FILE", str(tmp_path / "none"))
    monkeypatch.setenv("AWS_EC2_METADATA_DISABLED", "true")
    with pytest.raises(UserError, match=r"no credentials for s3://.*AWS_ACCESS_KEY_ID"):
        Storage.open(url, {"endpoint_url": options["endpoint_url"]})


def test_credentials_in_url_work_and_never_show(s3_server):
    bucket = create_bucket(s3_server)
    url = f"s3://{S3_KEY}:{S3_SECRET}@{bucket}/run"
    storage = Storage.open(url, {"endpoint_url": s3_server["endpoint_url"]})
    storage.write_exclusive("x", b"1")
    assert storage.read("x") == b"1"
    assert storage.url == f"s3://{bucket}/run" == display_url(url)
    assert S3_SECRET not in repr(storage) and S3_KEY not in repr(storage)
    with pytest.raises(FileNotFoundError) as missing:
        storage.read("nothing")
    with pytest.raises(UserError) as no_bucket:
        Storage.open(f"s3://{S3_KEY}:{S3_SECRET}@no-such-bucket/run", {"endpoint_url": s3_server["endpoint_url"]})
    for text in (str(missing.value), str(no_bucket.value)):
        assert S3_SECRET not in text and S3_KEY not in text


def test_unreachable_endpoint_is_unavailable_not_bad_input_after_bounded_attempts(caplog):
    """Nothing listens on the port: an infrastructure fault to wait out, never a UserError (exit 2)."""
    options = {"endpoint_url": f"http://127.0.0.1:{free_port()}"}
    caplog.set_level(logging.DEBUG, logger="ftrain.ckpt.storage")
    start = time.monotonic()
    with pytest.raises(StorageUnavailable, match=r"cannot reach the S3 endpoint .* after 3 attempts") as error:
        Storage.open(f"s3://{S3_KEY}:{S3_SECRET}@bucket/run", options, retries=2, base_delay=0.01)
    assert not isinstance(error.value, UserError)
    assert time.monotonic() - start < 15  # bounded: botocore alone would retry for minutes
    assert [r.levelno for r in caplog.records] == [logging.WARNING, logging.DEBUG]  # one line shown
    for text in (str(error.value), caplog.text):
        assert S3_SECRET not in text and S3_KEY not in text


class FlakyProxy:
    """A TCP proxy in front of the S3 server. While down it cuts live connections and drops new ones: what a
    network outage or a restarting server looks like to the client. ``lose_responses`` swallows that many
    final responses (the request was served) and cuts their connections."""

    def __init__(self, target: str):
        self.target = (urlsplit(target).hostname, urlsplit(target).port)
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.endpoint = f"http://127.0.0.1:{self.listener.getsockname()[1]}"
        self.up = threading.Event()
        self.up.set()
        self.refused = threading.Event()
        """Set once a connection was dropped during an outage: the client has really seen it."""
        self.live: list[socket.socket] = []
        self.lose_responses = 0
        self.back_after: int | None = None
        threading.Thread(target=self._accept, daemon=True).start()

    def down(self, connections: int | None = None) -> None:
        """Down until ``up`` is set again, or (``connections``) until it has dropped that many connections."""
        self.back_after = connections
        self.up.clear()
        for sock in self.live:
            _cut(sock)
        self.live.clear()

    def close(self) -> None:
        self.down()
        self.listener.close()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            if not self.up.is_set():
                client.close()
                self.refused.set()
                self.back_after = None if self.back_after is None else self.back_after - 1
                if self.back_after == 0:
                    self.up.set()
                continue
            upstream = socket.create_connection(self.target)
            self.live += [client, upstream]
            for src, dst, is_response in ((client, upstream, False), (upstream, client, True)):
                threading.Thread(target=self._pump, args=(src, dst, is_response), daemon=True).start()

    def _pump(self, src: socket.socket, dst: socket.socket, is_response: bool) -> None:
        try:
            while data := src.recv(65536):
                if is_response and self.lose_responses > 0 and not data.startswith(b"HTTP/1.1 100"):
                    self.lose_responses -= 1
                    break
                dst.sendall(data)
        except OSError:
            pass
        _cut(src)
        _cut(dst)


def _cut(sock: socket.socket) -> None:
    """Shut down (this wakes a thread blocked in recv and tells the peer), then close."""
    with contextlib.suppress(OSError):
        sock.shutdown(socket.SHUT_RDWR)
    sock.close()


@pytest.fixture
def flaky_s3(s3_server):
    """``(proxy, url)``: a bucket reached through a FlakyProxy, with credentials in the URL."""
    proxy = FlakyProxy(s3_server["endpoint_url"])
    yield proxy, f"s3://{S3_KEY}:{S3_SECRET}@{create_bucket(s3_server)}/run"
    proxy.close()


def test_transient_outage_is_retried(flaky_s3, caplog):
    proxy, url = flaky_s3
    storage = Storage.open(url, {"endpoint_url": proxy.endpoint}, retries=6, base_delay=0.05)
    storage.write_exclusive("checkpoints/step-1/MANIFEST.json", b"{}")
    caplog.set_level(logging.WARNING, logger="ftrain.ckpt.storage")
    proxy.down(connections=2)  # the outage ends after the client has hit it twice, however slow the machine
    assert storage.read("checkpoints/step-1/MANIFEST.json") == b"{}"
    assert 1 <= len(caplog.records) <= 2  # a line for a failing request, not one for each of its retries
    assert "retry 1/6 in " in caplog.text and "retry 2/" not in caplog.text and S3_SECRET not in caplog.text


def test_persistent_outage_raises_storage_error_after_bounded_attempts(flaky_s3, caplog):
    proxy, url = flaky_s3
    storage = Storage.open(url, {"endpoint_url": proxy.endpoint}, retries=3, base_delay=0.02)
    caplog.set_level(logging.DEBUG, logger="ftrain.ckpt.storage")
    proxy.down()
    start = time.monotonic()
    with pytest.raises(StorageError, match=r"read s3://.*/run/x failed after 4 attempts") as error:
        storage.read("x")
    assert time.monotonic() - start < 15  # bounded: botocore alone would retry for minutes
    assert [r.levelno for r in caplog.records] == [logging.WARNING] + [logging.DEBUG] * 2  # one line shown
    for text in (str(error.value), caplog.text):
        assert S3_SECRET not in text and S3_KEY not in text


def test_a_retried_create_whose_first_attempt_landed_succeeds(flaky_s3):
    """The first PUT lands but its response is lost; the retry is refused (the object exists) and finds its own
    bytes there: success. Other bytes under the same name stay a FileExistsError."""
    proxy, url = flaky_s3
    storage = Storage.open(url, {"endpoint_url": proxy.endpoint}, retries=2, base_delay=0.01)
    proxy.lose_responses = 1
    storage.write_exclusive("a", b"same")
    assert proxy.lose_responses == 0
    assert storage.read("a") == b"same"
    with pytest.raises(FileExistsError):
        storage.write_exclusive("a", b"other")


def test_display_url_strips_credentials():
    assert display_url("s3://k:s@bucket/p") == "s3://bucket/p"
    assert display_url("s3://bucket/p") == "s3://bucket/p"
    assert display_url("runs/hc") == "runs/hc"
    assert display_url("s3://") == "s3://"


def test_negative_retries_is_a_user_error(tmp_path):
    with pytest.raises(UserError, match="retries=-1"):
        Storage.open(str(tmp_path), retries=-1)


def test_a_local_file_is_complete_whenever_it_is_visible(tmp_path):
    """A reader polling the path while a large file is created never sees it partly written (a manifest is the
    commit: half a manifest must never be readable), and a create that loses to an existing file leaves no trace."""
    storage = Storage.open(str(tmp_path / "run"))
    data = os.urandom(64 << 20)
    path = tmp_path / "run" / "checkpoints" / "MANIFEST.json"
    sizes: list[int] = []
    done = threading.Event()

    def watch() -> None:
        while not done.is_set():
            with contextlib.suppress(FileNotFoundError):
                sizes.append(len(path.read_bytes()))

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        storage.write_exclusive("checkpoints/MANIFEST.json", data)
        deadline = time.monotonic() + 10
        while not sizes and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        done.set()
        watcher.join()
    assert sizes and set(sizes) == {len(data)}
    with pytest.raises(FileExistsError):
        storage.write_exclusive("checkpoints/MANIFEST.json", b"other")
    assert sorted(p.name for p in path.parent.iterdir()) == ["MANIFEST.json"]
    assert path.read_bytes() == data


def test_forked_processes_back_off_apart() -> None:
    """Warm workers are forks of one pool: each draws its own retry jitter, not the pool's sequence in step."""
    delays = []
    for _ in range(2):
        read, write = os.pipe()
        if (pid := os.fork()) == 0:
            os.write(write, repr([Backoff(1.0, 100.0).delay(3) for _ in range(4)]).encode())
            os._exit(0)
        os.close(write)
        os.waitpid(pid, 0)
        with os.fdopen(read) as pipe:
            delays.append(pipe.read())
    assert delays[0] != delays[1]


@pytest.mark.parametrize("code", [errno.EIO, errno.ESTALE, errno.ENOTCONN])
def test_a_failing_mount_is_an_outage_not_bad_input(tmp_path, code) -> None:
    """What a hung NFS or FUSE mount raises is retried, then reported as the storage being unavailable (the supervisor
    waits for it), not a crash; a file that is not there is still just missing."""
    storage = Storage.open(str(tmp_path), retries=1)
    calls = []

    def failing_mount() -> None:
        calls.append(code)
        raise OSError(code, os.strerror(code), str(tmp_path))

    with pytest.raises(StorageUnavailable, match="failed after 2 attempts"):
        storage._call("read", "x", failing_mount)
    assert calls == [code, code]
    with pytest.raises(FileNotFoundError):
        storage.read("missing")


def test_gcsfs_prints_no_traceback_for_a_request_the_storage_reports_itself() -> None:
    """gcsfs logs every request that ran out of its own retries with its traceback (four of them, 100 lines, before
    the one line of an unreachable storage); the storage's error says it. In a process of its own: pytest captures
    logging, where a command prints it."""
    code = textwrap.dedent(
        """
        import logging
        from ftrain.ckpt.storage import Storage
        Storage.open("gs://bucket/run", {"token": "anon", "endpoint_url": "http://127.0.0.1:1"})
        try:
            raise ConnectionError("Cannot connect to host")
        except ConnectionError as error:
            logging.getLogger("gcsfs").exception(f"_request out of retries on exception: {error}")  # as gcsfs does
        logging.getLogger("ftrain").warning("a warning of ftrain's own")
        """
    )
    done = subprocess.run([sys.executable, "-c", code], env=child_env(), capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stderr == "a warning of ftrain's own\n", done.stderr


def test_a_gcs_storage_that_does_not_answer_is_tried_by_our_retries_alone_and_told_within_seconds(tmp_path) -> None:
    """gcsfs retries each request itself (6 tries over half a minute) and takes no option for it; ftrain sends each
    once, so a server that cuts every connection sees exactly our tries of the request, the storage is reported
    unavailable (an outage the supervisor waits out) and not bad input, and a run started on it exits 7 with one
    line."""
    listener = socket.create_server(("127.0.0.1", 0))
    requests: list[bytes] = []

    def cut_every_connection() -> None:
        while True:
            try:
                connection, _ = listener.accept()
                request = connection.recv(65536)
            except OSError:
                return
            if request.startswith((b"GET ", b"POST ")):  # gcsfs's JSON API (its gRPC calls speak HTTP/2)
                requests.append(request.split(b"\r\n", 1)[0])
            connection.close()

    threading.Thread(target=cut_every_connection, daemon=True).start()
    options = {"token": "anon", "endpoint_url": f"http://127.0.0.1:{listener.getsockname()[1]}"}
    tries = {}
    for retries in (0, 2):
        requests.clear()
        storage = Storage.open("gs://bucket/run", options, retries=retries, base_delay=0.01)
        expected = rf"^read gs://bucket/run/LEASE.json failed after {retries + 1} attempts: ServerDisconnectedError"
        with pytest.raises(StorageUnavailable, match=expected) as down:
            storage.read("LEASE.json")
        assert not isinstance(down.value, UserError)
        tries[retries] = len(requests)
    # aiohttp sends a GET again once where a reused connection closed unanswered (whether it reuses one depends on
    # timing): 1 or 2 requests per try of ours; gcsfs's own retries would be 6 per try
    assert 1 <= tries[0] <= 2 and 3 <= tries[2] <= 6, tries
    listener.close()

    start = time.monotonic()
    options = ["storage.options.token=anon", f"storage.options.endpoint_url=http://127.0.0.1:{free_port()}"]
    command = [*train_command("gs://bucket/run", *options, f"log_dir={tmp_path / 'logs'}"), "iterations=1"]
    run = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=300)
    errors = [line for line in run.stderr.splitlines() if line.startswith("ftrain: error:")]
    assert run.returncode == EXIT_STORAGE_DOWN, run.stderr[-2000:]
    assert len(errors) == 1 and "failed after 5 attempts: ClientConnectorError" in errors[0], run.stderr[-2000:]
    assert "Traceback" not in run.stderr
    print(f"a run on a GCS storage that does not answer ended in {time.monotonic() - start:.0f} s")


@pytest.mark.parametrize(
    ("status", "message"),
    [
        (403, "ci@p.iam.gserviceaccount.com lacks storage.objects.get access to the Google Cloud Storage object"),
        (401, "Anonymous caller lacks storage.objects.get access to the Google Cloud Storage object"),
    ],
)
def test_a_gcs_storage_that_refuses_the_credentials_is_bad_input_told_in_one_line(tmp_path, status, message) -> None:
    """Google's answer to credentials without the permission (403) or to none (401), as its JSON API gives it: access
    denied, bad input that no wait fixes (gcsfs raises a 403 as a plain OSError), and a run on it exits 2, one line."""

    class Refusing(http.server.BaseHTTPRequestHandler):
        def refuse(self) -> None:
            body = json.dumps({"error": {"code": status, "message": message, "errors": [{"reason": "forbidden"}]}})
            self.send_response(status)
            self.send_header("Content-Type", "application/json; charset=UTF-8")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body.encode())

        do_GET = do_POST = do_PUT = do_DELETE = refuse

        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Refusing)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    endpoint = f"http://127.0.0.1:{server.server_address[1]}"
    try:
        storage = Storage.open("gs://bucket/run", {"token": "anon", "endpoint_url": endpoint}, base_delay=0.01)
        with pytest.raises(UserError, match=r"^access denied to gs://bucket/run \(.*\): check the credentials"):
            storage.read("LEASE.json")
        options = ["storage.options.token=anon", f"storage.options.endpoint_url={endpoint}"]
        command = [*train_command("gs://bucket/run", *options, f"log_dir={tmp_path / 'logs'}"), "iterations=1"]
        run = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=300)
    finally:
        server.shutdown()
    errors = [line for line in run.stderr.splitlines() if line.startswith("ftrain: error:")]
    assert run.returncode == EXIT_USAGE, run.stderr[-2000:]
    assert len(errors) == 1 and "access denied to gs://bucket/run" in errors[0], run.stderr[-2000:]
    assert "Traceback" not in run.stderr


def test_a_file_url_is_read_as_rfc_8089_reads_it(tmp_path) -> None:
    """``file:///a%20b`` and ``file://localhost/a%20b`` name the directory ``/a b`` (fsspec alone takes both
    literally: a fresh run in another directory, next to the one to resume). Generated names, each written through
    four URL forms, found at the decoded path and named by it."""
    draw = random.Random(8089)
    alphabet = "ab z%#?é+&;"
    checked, names = 0, set()
    for number in range(60):
        name = f"{number}-" + "".join(draw.choice(alphabet) for _ in range(draw.randint(1, 8)))
        names.add(name)
        for prefix in ("file://", "file://localhost", "local://", "FILE://"):
            storage = Storage.open(prefix + quote(str(tmp_path / name)))
            assert storage.url == str(tmp_path / name), (prefix, name)  # what every line names: the path itself
            storage.write_replace(f"from-{len(prefix)}", b"x")
            assert (tmp_path / name / f"from-{len(prefix)}").read_bytes() == b"x", (prefix, name)
            checked += 1
    print(f"{checked} file URLs checked")
    assert set(os.listdir(tmp_path)) == names  # nothing written under a literal name or a "localhost" directory


@pytest.mark.parametrize(
    ("url", "line"),
    [
        ("file://tmp/x", "names the host 'tmp': write file:///tmp/x (three slashes) for the absolute path /tmp/x"),
        ("file://otherhost/data/run", "names the host 'otherhost'"),
        ("file:///tmp/a%00b", "holds a NUL byte, which no path can: fix the path"),
    ],
)
def test_a_local_url_that_names_another_host_or_holds_a_nul_is_one_line_and_writes_nothing(tmp_path, url, line):
    """``file://tmp/x`` is one slash short: fsspec would write a directory ``tmp`` in the current directory."""
    result = subprocess.run(
        [sys.executable, "-m", "ftrain", "ckpt", "ls", url],
        cwd=tmp_path,
        env=child_env(),
        capture_output=True,
        text=True,
    )
    assert result.returncode == EXIT_USAGE and line in result.stderr and "Traceback" not in result.stderr, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and os.listdir(tmp_path) == []


def test_a_run_started_on_a_file_url_resumes_from_its_plain_path(tmp_path) -> None:
    run = tmp_path / "my run"
    url = "file://" + quote(str(run))
    first = subprocess.run(train_command(url, "iterations=2"), env=child_env(), capture_output=True, text=True)
    assert first.returncode == 0, first.stderr[-2000:]
    assert Storage.open(str(run)).list_dirs("checkpoints") == ["step-000000002"]
    assert (run / "metrics.csv").exists()  # the logs went next to the checkpoints, in the same directory
    command = train_command(run, "iterations=3", "log.console=true")
    second = subprocess.run(command, env=child_env(), capture_output=True, text=True)
    assert second.returncode == 0, second.stderr[-2000:]
    assert "resum" in (second.stdout + second.stderr).lower()
    hint = next(line for line in second.stdout.splitlines() if line.startswith("[ftrain] play it: "))
    assert shlex.split(hint.removeprefix("[ftrain] play it: "))[:3] == ["ftrain", "play", str(run)], hint
    assert Storage.open(url).list_dirs("checkpoints")[-1] == "step-000000003"
