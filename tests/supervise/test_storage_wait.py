"""The supervisor's wait for a storage that does not answer shows on a terminal how long it has waited, and leaves no
trace of that line in its messages. A real S3 client knocking at a port where nothing listens."""

from __future__ import annotations

import contextlib
import os
import pty
import random
import re
import sys

from ftrain.ckpt.storage import Storage
from ftrain.config import StorageConfig
from ftrain.redact import Url
from ftrain.supervise.events import EventLog
from ftrain.supervise.options import EXIT_STORAGE_WAIT
from ftrain.supervise.outage import StorageWait

from helpers import ManualClock, flip_shard_byte, free_port, make_step


def test_a_storage_wait_on_a_terminal_shows_how_long_it_has_waited(tmp_path, monkeypatch) -> None:
    ours, theirs = pty.openpty()
    terminal = os.fdopen(theirs, "w")
    monkeypatch.setattr(sys, "stderr", terminal)
    options = {"endpoint_url": f"http://127.0.0.1:{free_port()}", "key": "k", "secret": "s"}
    clock = ManualClock()  # moves only while the wait sleeps: a probe takes 0.4-5 s, by how busy the machine is
    storage = StorageConfig(Url("s3://bucket/run"), options)
    wait = StorageWait(storage, 1.0, EventLog(tmp_path / "events", 0), clock.sleep, clock=clock)
    outcome = wait("refused")
    terminal.close()
    shown = b""
    with contextlib.suppress(OSError):  # EIO once all is read: the terminal's other side is closed
        while chunk := os.read(ours, 4096):
            shown += chunk
    os.close(ours)
    text = shown.decode()
    assert outcome.code == EXIT_STORAGE_WAIT
    live = re.search(r"\r(ftrain supervise: waiting for storage s3://bucket/run: 0s of at most 1s\.\.\.)\r( *)\r", text)
    assert live and len(live[2]) == len(live[1]), repr(text)  # drawn, then wiped before anything else
    assert text.startswith("ftrain supervise: storage s3://bucket/run has not answered"), repr(text)


def test_the_storage_holds_a_step_only_while_it_verifies(tmp_path) -> None:
    """What a node checks before it ends a run as finished without launching: the step committed and intact, as a
    resume would load it (a flipped byte in a shard is a step to fall back from, not a finished run)."""
    storage = Storage.open(str(tmp_path / "run"))
    wait = StorageWait(StorageConfig(Url(str(tmp_path / "run"))), 1.0, EventLog(tmp_path / "events", 0), lambda s: None)
    assert not wait.holds(4)
    make_step(storage, 4)
    assert wait.holds(4) and not wait.holds(8)
    flip_shard_byte(storage, 4)
    assert not wait.holds(4)


def test_attempts_that_find_the_storage_unusable_one_after_another_back_off_and_share_one_limit(tmp_path) -> None:
    """A storage that answers the probe (it lists) but fails the workers before they train an iteration must not be
    restarted into without end: each such attempt after the first backs off (1 s, doubling, at most 60) and their
    time counts to one ``--storage-wait``, which an attempt that trained starts again. Random schedules of attempts
    against a real local storage, time on a manual clock."""
    rng = random.Random(52)
    limit, checked = 200.0, 0
    storage = StorageConfig(Url(str(tmp_path / "run")))
    Storage.open(str(tmp_path / "run"))
    for _ in range(60):
        clock = ManualClock()
        wait = StorageWait(storage, limit, EventLog(tmp_path / "events", 0), clock.sleep, clock=clock, log_dir=tmp_path)
        began, fruitless = None, 0
        for _ in range(rng.randint(1, 40)):
            again = began is not None and rng.random() < 0.8  # the attempt since the last wait trained nothing
            if not again:
                began, fruitless = clock(), 0
            before = clock()
            outcome = wait("rank 0: the storage refused a request", again=again)
            slept = clock() - before
            checked += 1
            if not again:
                assert outcome is None and slept == 0  # it answers: restart at once, a wait of its own
                continue
            if before - began > limit:
                assert outcome is not None and outcome.code == EXIT_STORAGE_WAIT and slept == 0
                break
            assert outcome is None
            assert 0.75 * min(2**fruitless, 60) <= slept <= 1.25 * min(2**fruitless, 60)
            fruitless += 1
    print(f"{checked} waits checked")
    assert checked > 300
