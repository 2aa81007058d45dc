"""One history per storage, as a property: seeded random schedules of contending runs (``history_chaos``) on a local
directory, moto's S3 (refusing connections now and then) and Azurite (paused now and then), each checked over the
storage's whole history. The suite runs one schedule per backend; ``FTRAIN_HISTORY_SCHEDULES=N`` runs N per backend
(the long lane: ``FTRAIN_HISTORY_SCHEDULES=10 launch/test.sh tests/ckpt/test_one_history.py``). Each test prints
what it checked (``pytest -s``, or the summary of ``-rA``)."""

from __future__ import annotations

import os
import shutil
import signal
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from history_chaos import OVERRIDES, Schedule, Tally, Watcher, check

from ftrain.ckpt.storage import Storage

from helpers import (
    S3_KEY,
    S3_REGION,
    S3_SECRET,
    azurite_blob,
    create_bucket,
    create_container,
    final_manifest,
    free_port,
    run_train,
    start_azurite,
)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        os.geteuid() != 0 or not shutil.which("unshare"), reason="users on hosts of their own: unshare --uts, as root"
    ),
]

ITERATIONS = 120
SCHEDULES = int(os.environ.get("FTRAIN_HISTORY_SCHEDULES", "1"))
OPERATIONS = 12


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> str:
    """The final state of the same run, undisturbed and alone."""
    storage = tmp_path_factory.mktemp("reference") / "run"
    run_train(storage, f"iterations={ITERATIONS}", *OVERRIDES)
    return final_manifest(storage)["state_sha256"]


def histories(
    first_seed: int,
    storage_of: Callable[[], tuple[str, dict | None]],
    env: dict,
    workdir: Path,
    reference: str,
    local: bool,
    outage: Callable[[float], None] | None = None,
) -> Tally:
    """``SCHEDULES`` seeded histories, each on a fresh storage from ``storage_of``; what was checked."""
    tally = Tally()
    for seed in range(first_seed, first_seed + SCHEDULES):
        url, options = storage_of()
        storage = Storage.open(url, options)
        schedule = Schedule(seed, url, env, workdir / f"seed-{seed}", ITERATIONS, OPERATIONS, outage)
        schedule.workdir.mkdir(parents=True)
        watcher = Watcher(storage)
        watcher.start()
        try:
            schedule.play(tally)
            schedule.finish(tally)
        finally:
            schedule.kill_all()
            watcher.stop.set()
            watcher.join()
        watcher.poll(0)  # a last look, every user gone
        check(storage, watcher, reference, local, tally)
    print(f"seeds {first_seed}-{first_seed + SCHEDULES - 1}: {tally.line()}")
    assert tally.histories == SCHEDULES and tally.commits > 0
    return tally


def test_on_a_local_directory(tmp_path, reference):
    """From schedule 1003: three users under one run id, one with a clock 20 s behind (the code that joined two starts
    of one run id forked it); the S3 and Azure schedules have users of their own ids too."""
    runs = iter(range(SCHEDULES))
    histories(1003, lambda: (str(tmp_path / f"run-{next(runs)}"), None), {}, tmp_path, reference, local=True)


def test_on_s3_refusing_connections_now_and_then(tmp_path, reference, s3_outage):
    server = s3_outage.server
    direct = {"endpoint_url": server.direct_url, "key": S3_KEY, "secret": S3_SECRET, "region": S3_REGION}

    def outage(seconds: float) -> None:
        server.refuse()
        time.sleep(seconds)
        server.restore()

    storage_of = lambda: (f"s3://{create_bucket(direct)}/run", s3_outage.options)  # noqa: E731
    histories(2000, storage_of, s3_outage.env, tmp_path, reference, local=False, outage=outage)


def test_on_azure_blob_storage_paused_now_and_then(tmp_path, reference):
    pytest.importorskip("adlfs", reason="adlfs is not installed (pip install -e '.[azure]')")
    command = azurite_blob()
    if command is None:
        pytest.skip("Azurite is not installed: launch/setup.sh installs it with npm when FTRAIN_TEST_DEPS=1")
    proc, server = start_azurite(command, free_port(), tmp_path)

    def outage(seconds: float) -> None:
        proc.send_signal(signal.SIGSTOP)
        time.sleep(seconds)
        proc.send_signal(signal.SIGCONT)

    options = {"connection_string": server["connection_string"]}
    env = {"AZURE_STORAGE_CONNECTION_STRING": server["connection_string"]}
    try:
        storage_of = lambda: (f"abfs://{create_container(server)}/run", options)  # noqa: E731
        histories(3000, storage_of, env, tmp_path, reference, local=False, outage=outage)
    finally:
        proc.send_signal(signal.SIGCONT)
        proc.kill()
        proc.wait()
