"""The supervisor's wait for a storage that does not answer shows on a terminal how long it has waited, and leaves no
trace of that line in its messages. A real S3 client knocking at a port where nothing listens."""

from __future__ import annotations

import contextlib
import os
import pty
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
