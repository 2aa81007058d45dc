"""One history under random faults: a seeded schedule of 2-4 users who run the same ``ftrain train`` command on one
storage, each from a host of its own (a UTS namespace: another host name, so that only a lease's expiry frees its
storage), some with a wall clock off by seconds (``tests/skewed_clock``), some under one shared run id (one
``FTRAIN_RUN_ID``: launches that are not nodes of one run, whose second start takes the storage from the first), while
the schedule starts them, SIGKILLs them, SIGSTOPs them for longer than the lease's time to live and cuts the storage
off; then a last user trains the run to its end.

A watcher reads the storage throughout: each poll reads the lease, then lists the manifests. A manifest of generation
g that first appears after a poll whose lease read already had a newer generation was written after the lease had
moved on (a late commit). What ``check`` asserts of the storage's whole history:
- one holder at a time: the lease never names two processes (each user's run is one process; users that share a run
  id are two launches, not two nodes of one run, and deterministic alike, so their interleaved commits would
  otherwise pass for one history);
- one lineage (``lineage.history``: no fork), its generations never decreasing along the line;
- no late commit on a file system (the holder's check runs under the lease's lock there); on an object store, every
  late commit superseded by the newer generation's line, or on the line itself;
- every manifest the watcher ever saw is still there, in ``checkpoints/`` or set aside in ``quarantine/``: retention
  is off (``keep_last`` above the run's steps), so nothing verified may go;
- the final state bit-equal to an undisturbed run of the same seed.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

from ftrain.ckpt.lease import TTL_ENV, read_record
from ftrain.ckpt.lineage import generation, history
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.identity import RUN_ID_ENV

from helpers import REPO, SMOKE, TESTS, child_env

SKEW_ENV = "FTRAIN_TEST_CLOCK_SKEW"
"""Seconds a user's wall clock is off (``tests/skewed_clock/sitecustomize.py``)."""
TTL = 2.0
"""The lease's time to live in these runs (renewed every third of it)."""
OVERRIDES = ("checkpoint.interval=4", "checkpoint.keep_last=100000", "checkpoint.keep_best=0", "log.console=false")
SHARED_RUN_ID = "job-1"
"""The run id (``FTRAIN_RUN_ID``) of the users that share one; the others draw their own at every start (rank 0)."""
SKEWS = (0.0, 0.0, -20.0, 3.0)
"""Each user's clock: most right, one 20 s behind (its lease would look expired to the others but for the storage's
own clock), one a little ahead."""
STARTUP = 4.0
"""Seconds after its start from which a user's run is hit by faults: before that it imports (torch, MuJoCo)."""


@dataclasses.dataclass
class Tally:
    histories: int = 0
    starts: int = 0
    shared_id_starts: int = 0
    refused: int = 0
    kills: int = 0
    pauses: int = 0
    outages: int = 0
    commits: int = 0
    late: int = 0
    superseded: int = 0
    generations: int = 0

    @property
    def operations(self) -> int:
        return self.starts + self.kills + self.pauses + self.outages + self.commits + self.generations

    def line(self) -> str:
        return (
            f"one history held in {self.histories} histories, {self.operations} operations checked: {self.starts} "
            f"starts ({self.shared_id_starts} under a run id users share, {self.refused} refused), {self.kills} "
            f"SIGKILLs, {self.pauses} pauses past the lease, "
            f"{self.outages} storage outages, {self.generations} lease generations, {self.commits} commits "
            f"({self.late} late, {self.superseded} superseded)"
        )


@dataclasses.dataclass
class User:
    host: str
    skew: float
    log: Path
    run_id: str | None = None
    proc: subprocess.Popen | None = None
    started: float = 0.0
    paused_until: float | None = None

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


class Watcher(threading.Thread):
    """Polls the lease, then the manifests, until stopped: every manifest seen (by path: its bytes), the late ones."""

    def __init__(self, storage: Storage) -> None:
        super().__init__(daemon=True)
        self.storage = storage
        self.seen: dict[str, bytes] = {}
        self.late: set[str] = set()
        self.generations: set[int] = set()
        self.most_holders = 0
        """The most processes the lease named at once: each user is one process, never a node of another's run."""
        self.stop = threading.Event()

    def run(self) -> None:
        previous = 0
        while not self.stop.wait(0.05):
            with contextlib.suppress(Exception):  # an outage: the next poll looks again
                previous = self.poll(previous)

    def poll(self, previous: int) -> int:
        current = read_record(self.storage)
        lease = current[0].generation if current is not None else 0
        self.most_holders = max(self.most_holders, len(current[0].entries) if current is not None else 0)
        for path in manifests(self.storage):
            if path not in self.seen:
                data = self.storage.fs.cat_file(path)
                self.seen[path] = data
                if json.loads(data).get("generation", 0) < previous:  # absent from a listing made after that lease
                    self.late.add(path)
        self.generations.add(lease)
        return lease


def manifests(storage: Storage, under: str = "checkpoints") -> list[str]:
    storage.forget_listing(under)
    found = storage.fs.find(f"{storage.root}/{under}")
    return sorted(path for path in found if path.endswith("/MANIFEST.json"))


class Schedule:
    """One seeded history on one storage: ``users`` users, ``operations`` random operations, then the last user's run
    to ``iterations``. ``outage(seconds)``: cut the storage off for that long (None: this backend has none)."""

    def __init__(
        self,
        seed: int,
        url: str,
        env: dict,
        workdir: Path,
        iterations: int,
        operations: int,
        outage: Callable[[float], None] | None,
    ) -> None:
        self.rng = random.Random(seed)
        self.url, self.env, self.workdir, self.iterations = url, env, workdir, iterations
        self.operations, self.outage = operations, outage
        count = self.rng.randint(2, 4)
        self.users = [User(f"user-{i}", self.rng.choice(SKEWS), workdir / f"user-{i}.log") for i in range(count)]
        for user in self.rng.sample(self.users, self.rng.randint(0, count)):
            user.run_id = SHARED_RUN_ID

    def command(self, user: User) -> list[str]:
        host = ["unshare", "--uts", "sh", "-c", f'hostname {user.host} && exec "$@"', "sh"]
        train = [sys.executable, "-m", "ftrain", "train", SMOKE, "--storage", self.url, f"iterations={self.iterations}"]
        return [*host, *train, *OVERRIDES, f"log_dir={self.workdir / user.host}"]

    def start(self, user: User, tally: Tally) -> None:
        clock = {"PYTHONPATH": str(TESTS / "skewed_clock"), SKEW_ENV: str(user.skew)}
        run_id = {RUN_ID_ENV: user.run_id} if user.run_id else {}
        env = child_env({**self.env, TTL_ENV: str(TTL), **clock, **run_id})
        with user.log.open("ab") as log:
            user.proc = subprocess.Popen(
                self.command(user), cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        user.started = time.monotonic()
        tally.starts += 1
        tally.shared_id_starts += user.run_id is not None

    def play(self, tally: Tally) -> None:
        """The random part: each operation, then a random wait; paused users go on when their pause is over."""
        for _ in range(self.operations):
            self._continue_paused()
            now = time.monotonic()  # a fault hits a user once it has started up (imports take seconds) and trains
            running = [u for u in self.users if u.running and u.paused_until is None and now - u.started > STARTUP]
            idle = [user for user in self.users if not user.running]
            kinds = ["start"] * bool(idle) + ["kill", "pause"] * bool(running) + ["outage"] * bool(self.outage)
            kind = self.rng.choice([*kinds, "wait"])
            if kind == "start":
                self.start(self.rng.choice(idle), tally)
            elif kind == "kill":
                os.killpg(self.rng.choice(running).proc.pid, signal.SIGKILL)
                tally.kills += 1
            elif kind == "pause":
                user = self.rng.choice(running)
                os.killpg(user.proc.pid, signal.SIGSTOP)
                user.paused_until = time.monotonic() + TTL * self.rng.uniform(1.3, 2.5)
                tally.pauses += 1
            elif kind == "outage":
                self.outage(self.rng.uniform(0.5, TTL * 1.5))
                tally.outages += 1
            time.sleep(self.rng.uniform(0.5, 3.0))

    def finish(self, tally: Tally, timeout: float = 240) -> None:
        """Every paused user goes on; every user still running is killed; then the last user trains to the end (it
        is refused while a killed user's lease has not expired yet, and starts again)."""
        for user in self.users:
            if user.paused_until is not None:
                user.paused_until = 0.0
        self._continue_paused()
        time.sleep(1.0)  # the users that went on meet the lease they lost
        for user in self.users:
            if user.running:
                os.killpg(user.proc.pid, signal.SIGKILL)
                tally.kills += 1
            if user.proc is not None:
                user.proc.wait(timeout=60)
        self._check_endings(tally)
        last, deadline = self.users[0], time.monotonic() + timeout
        while True:
            self.start(last, tally)
            code = last.proc.wait(timeout=max(1.0, deadline - time.monotonic()))
            if code == 0:
                return
            assert code == 8 and time.monotonic() < deadline, f"the last run ended {code}: see {last.log}"
            tally.refused += 1
            time.sleep(0.5)

    def kill_all(self) -> None:
        for user in self.users:
            if user.proc is not None and user.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(user.proc.pid, signal.SIGCONT)
                    os.killpg(user.proc.pid, signal.SIGKILL)

    def _continue_paused(self) -> None:
        for user in self.users:
            if user.paused_until is not None and time.monotonic() >= user.paused_until:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(user.proc.pid, signal.SIGCONT)
                user.paused_until = None

    def _check_endings(self, tally: Tally) -> None:
        for user in self.users:
            said = user.log.read_text(errors="replace") if user.log.exists() else ""
            assert "Traceback" not in said, f"{user.host}: a traceback in {user.log}"
            tally.refused += said.count("is held by another run")


def check(storage: Storage, watcher: Watcher, reference: str, local: bool, tally: Tally) -> None:
    """The invariants of the module's doc, over the storage's whole history; ``tally`` counts what was checked."""
    assert watcher.most_holders <= 1, f"the lease named {watcher.most_holders} holders at once: two runs wrote"
    infos = scan(storage)
    past = history(infos)
    assert past.forks == [], past.fork_message(storage.url)
    by_step = {info.step: info for info in infos}
    line = [generation(by_step[step]) for step in sorted(past.line)]
    assert line == sorted(line), f"generations along the line must not decrease: {line}"
    if local:
        assert not watcher.late, f"commits after the lease had moved on: {sorted(watcher.late)}"
    superseded = {step_of(path) for path in watcher.late} - set(past.line)
    assert superseded <= set(past.superseded) | set(aside(storage)), (superseded, past)
    present = {info.step for info in infos if info.manifest}
    for step, older in zip(sorted(past.line, reverse=True), sorted(past.line, reverse=True)[1:], strict=False):
        parent = by_step[step].manifest["parent"]  # read here, not through lineage: its parent, or one never kept
        assert parent["step"] == older or parent["step"] not in present, (step, parent, older)
    now = {path: storage.fs.cat_file(path) for path in manifests(storage)}
    set_aside = {storage.fs.cat_file(path) for path in manifests(storage, "quarantine")}
    for path, data in watcher.seen.items():
        assert now.get(path) == data or data in set_aside, f"a verified step went, or changed: {path}"
    newest = by_step[max(past.line)].manifest
    assert newest["state_sha256"] == reference, "the last holder's final state must be the undisturbed run's"
    tally.histories += 1
    tally.commits += len(watcher.seen)
    tally.late += len(watcher.late)
    tally.superseded += len(past.superseded) + len(aside(storage))
    tally.generations += len(watcher.generations - {0})


def step_of(path: str) -> int:
    return int(path.rstrip("/").split("/")[-2].removeprefix("step-"))


def aside(storage: Storage) -> list[int]:
    """The steps set aside under ``quarantine/`` as superseded."""
    found = []
    for path in manifests(storage, "quarantine"):
        marker = path.replace("MANIFEST.json", "QUARANTINED.json")
        with contextlib.suppress(FileNotFoundError):
            if "superseded" in json.loads(storage.fs.cat_file(marker))["reason"]:
                found.append(step_of(path))
    return found
