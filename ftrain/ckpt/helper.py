"""The save helper: one process next to each rank that encodes, writes, agrees on and commits its rank's saves.

Why a process: a save's own work (``torch.save``, SHA-256, fsspec and S3 client calls, JSON, agreeing with the
other ranks) is Python that holds the GIL, plus gloo threads that wake up. On a background thread of the trainer it
landed on the training loop's critical path: 15-25% of throughput at a checkpoint every iteration on 2 busy cores,
measured here. The helper runs at idle CPU priority (``SCHED_IDLE``), so it works while a core would otherwise
wait. It dies with its rank (``PR_SET_PDEATHSIG``), ignores SIGTERM and SIGINT (a stop request is for the rank,
whose stop save the helper then writes) and is not marked as a worker for the supervisor.

Protocol, over a socket pair, each message a pickle: inline in the packet when it is small, else in an anonymous
shared memory file whose descriptor is sent. The rank sends ``(config, rank info, store prefix)`` and the helper
answers ``("ready", None)`` or ``("error", why)``; then the rank sends one ``(step, files, meta, check_loadable,
replace)`` per save and reads the outcomes back in order when it wants them: ``("committed", step, manifest)``,
``("failed", step, why)`` or ``("unloadable", step, why)``. A save's state is packed straight into the shared
memory (:class:`Slot`) and its flat tensors travel as offsets into it, so handing over a save is one copy of the
tensors, a small pickle and a few system calls; the rank reuses a slot once the save's outcome is back. The helpers
of all ranks meet in torchrun's key-value store (:class:`Meeting`), so a save never touches the training group. For
``memory://`` storage (one process only) the same loop runs on a thread instead.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import datetime
import os
import pickle
import select
import signal
import socket
import subprocess
import sys
import threading

import torch
import torch.distributed as dist

from ftrain.ckpt import packing
from ftrain.ckpt.format import (
    COMMON,
    INCOMPLETE,
    VERIFIED,
    CorruptCheckpoint,
    StepInfo,
    commit,
    decode,
    encode,
    write_file,
)
from ftrain.ckpt.handover import Slot, place, placed_tensors, receive, send
from ftrain.ckpt.retention import delete_step, retention_plan
from ftrain.ckpt.steps import replace_bad, scan
from ftrain.ckpt.storage import Storage
from ftrain.config import Config
from ftrain.dist import group
from ftrain.heartbeat import TOKEN_ENV

PR_SET_PDEATHSIG = 1
UNLOADABLE_HINT = "hooks and metrics must keep plain data (tensors, numbers, strings, lists, dicts)"


class SaverGone(RuntimeError):
    """The save helper is no longer there (it died, or the socket broke)."""


class Saver:
    """What the helper does for one rank: write its files, agree with the other ranks, commit on rank 0."""

    def __init__(self, config: Config, info: group.RankInfo, prefix: str) -> None:
        self.config = config
        self.info = info
        self.storage = Storage.open(config.storage.url, config.storage.options, retries=config.checkpoint.retries)
        self.meeting = Meeting(info, prefix, datetime.timedelta(seconds=config.dist_timeout))
        self._steps: dict[int, StepInfo] = {}
        """Rank 0: the steps in storage, scanned at the first save and then kept up to date by this run's own saves
        and deletions, so that retention needs no listing after every commit."""
        self._scanned = False
        self._listed = False
        """Rank 0: whether a commit has listed its step directory. The first one does: a storage that the ranks do
        not share (node-local directories on several nodes) shows there, once. Later commits trust the writers'
        own successful exclusive creates (a listing is a request per save on S3)."""

    def save(self, step: int, files: dict[str, dict], meta: dict | None, check_loadable: bool, replace: bool) -> tuple:
        """Write this rank's packed ``files`` of ``step``, then agree with the other ranks on the outcome.

        ``replace``: a corrupt or quarantined directory holds ``step``; rank 0 deletes it before anyone writes.
        """
        entries, fields, error, unloadable = {}, {}, None, False
        try:
            self._prepare(step, replace)
        except Exception as exc:
            error = f"rank {self.info.rank}: {exc}"
        if replace:
            self.meeting.replaced(step)  # nobody writes into the directory before rank 0 has deleted it
        if error is None:
            try:
                entries, fields = self._write(step, files, check_loadable)
            except CorruptCheckpoint as exc:  # only the loadability check raises it
                error, unloadable = f"rank {self.info.rank}: {exc}: {UNLOADABLE_HINT}", True
            except Exception as exc:  # any storage failure: reported, agreed on, never fatal by itself
                error = f"rank {self.info.rank}: {exc}"
        reports = self.meeting.gather(step, (entries, fields, error, unloadable))
        outcome = self._commit(step, reports, meta) if self.info.is_main else None
        return self.meeting.share(step, outcome)

    def _write(self, step: int, files: dict[str, dict], check_loadable: bool) -> tuple[dict, dict]:
        """Encode and write ``files``: their manifest entries, and the manifest fields that come from common.pt."""
        encoded = {name: encode(state) for name, state in files.items()}
        if check_loadable:
            for name, data in encoded.items():
                decode(data, name)
        fields = {}
        if COMMON in files:
            common = files[COMMON]
            fields["state_sha256"] = packing.digest(common, "learned")
            if "teacher" in common["tree"]:  # plain data: source, step, digest
                fields["teacher"] = common["tree"]["teacher"]
        entries = {name: write_file(self.storage, step, name, data) for name, data in encoded.items()}
        return entries, fields

    def _prepare(self, step: int, replace: bool) -> None:
        """Rank 0: scan the storage at the first save; delete the corrupt or quarantined directory of ``step``."""
        if not self.info.is_main:
            return
        if not self._scanned:
            self._steps |= {info.step: info for info in scan(self.storage)}
            self._scanned = True
        if replace:
            replace_bad(self.storage, step, log=log)
            self._steps.pop(step, None)

    def _commit(self, step: int, reports: list, meta: dict) -> tuple:
        errors = [error for _, _, error, _ in reports if error]
        if any(unloadable for *_, unloadable in reports):
            return ("unloadable", step, "; ".join(errors))
        files = {name: entry for entries, *_ in reports for name, entry in entries.items()}
        fields = {key: value for _, written, *_ in reports for key, value in written.items()}  # from common.pt
        if not errors:
            try:
                manifest = commit(self.storage, step, files, meta | fields, check_present=not self._listed)
                self._listed = True
            except Exception as exc:
                errors = [f"commit: {exc}"]
        if errors:
            self._steps[step] = StepInfo(step, INCOMPLETE)  # abandoned: retention deletes it
            return ("failed", step, "; ".join(errors))
        size = sum(entry.size for entry in files.values())
        self._steps[step] = StepInfo(step, VERIFIED, size, manifest)
        self._apply_retention()
        return ("committed", step, manifest)

    def _apply_retention(self) -> None:
        """Delete what the retention rules let go; a step that cannot be deleted now is kept and tried again later."""
        policy = self.config.checkpoint
        doomed = retention_plan(
            self._steps.values(),
            policy.keep_last,
            policy.keep_best,
            policy.best_metric,
            policy.keep_every,
            policy.pinned,
        )
        for step in doomed:
            try:
                delete_step(self.storage, step, self._steps[step].files)
            except Exception as exc:
                log(f"retention: checkpoint step {step} could not be deleted (kept for now): {exc}")
                continue
            del self._steps[step]


class Meeting:
    """Where the helpers of all ranks meet for each save: torchrun's key-value store, a few small requests per save.
    (A gloo group of the helpers took about 0.7 ms of CPU per collective here, more than the rest of a save.)"""

    def __init__(self, info: group.RankInfo, prefix: str, timeout: datetime.timedelta) -> None:
        self.info = info
        self.store: dist.Store | None = None
        if info.distributed:
            address, port = os.environ["MASTER_ADDR"], int(os.environ["MASTER_PORT"])
            self.store = dist.PrefixStore(prefix, dist.TCPStore(address, port, timeout=timeout))
        self._shared: str | None = None

    def gather(self, step: int, report: object) -> list | None:
        """Every rank's ``report`` in rank order, on rank 0 (None elsewhere)."""
        if self.store is None:
            return [report]
        if not self.info.is_main:
            self.store.set(f"{step}/report/{self.info.rank}", pickle.dumps(report))
            return None
        reports = [report]
        for rank in range(1, self.info.world_size):
            key = f"{step}/report/{rank}"
            reports.append(pickle.loads(self.store.get(key)))
            self.store.delete_key(key)
        if self._shared is not None:  # every rank has read the last outcome: it reported this save after that
            self.store.delete_key(self._shared)
        return reports

    def share(self, step: int, outcome: object) -> object:
        """Rank 0's ``outcome`` on every rank."""
        if self.store is None:
            return outcome
        key = f"{step}/outcome"
        if self.info.is_main:
            self.store.set(key, pickle.dumps(outcome))
            self._shared = key
            return outcome
        return pickle.loads(self.store.get(key))

    def replaced(self, step: int) -> None:
        """Rank 0 says it has deleted the bad directory of ``step``; the other ranks wait for that."""
        if self.store is None:
            return
        key = f"{step}/replaced"
        if self.info.is_main:
            self.store.set(key, b"")
        else:
            self.store.get(key)


class SaverClient:
    """The rank's end: starts the helper, sends it saves, reads their outcomes."""

    def __init__(self, config: Config, info: group.RankInfo) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock = ours
        self._proc: subprocess.Popen | None = None
        self._thread: threading.Thread | None = None
        if config.storage.url.startswith("memory://"):  # lives in this process: a thread must do
            self._thread = threading.Thread(target=serve, args=(theirs,), name="ftrain-saver", daemon=True)
            self._thread.start()
        else:
            code = (  # idle priority first, so that even its imports only take CPU time that training leaves
                "import os; os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0)); "
                f"from ftrain.ckpt.helper import helper_main; helper_main({theirs.fileno()}, {os.getpid()})"
            )
            env = {key: value for key, value in os.environ.items() if key != TOKEN_ENV}  # not a worker
            self._proc = subprocess.Popen(
                [sys.executable, "-c", code], pass_fds=(theirs.fileno(),), env=env, stdin=subprocess.DEVNULL
            )
            theirs.close()
        self._ready = False
        self._free: list[Slot] = []
        self._busy: collections.deque[Slot] = collections.deque()
        """The slots of the saves sent whose outcome has not been received, oldest first."""
        self._send((config, info, _store_prefix()))

    def save(self, step: int, states: dict[str, dict], meta: dict | None, check_loadable: bool, replace: bool) -> None:
        """Snapshot ``states`` (file name to state) into shared memory and send them as the save of ``step``."""
        slot = self._free.pop() if self._free else Slot()
        try:
            self._send((step, place(states, slot), meta, check_loadable, replace), slot)
        except BaseException:
            self._free.append(slot)
            raise
        self._busy.append(slot)

    def _send(self, message: object, slot: Slot | None = None) -> None:
        try:
            send(self._sock, message, slot)
        except OSError as exc:
            raise SaverGone(f"the checkpoint save helper is gone ({exc})") from None

    def wait_ready(self) -> None:
        """Wait until the helper has started and joined the other ranks' helpers (the first save waits anyway)."""
        if not self._ready:
            kind, why = self._receive()
            if kind != "ready":
                raise SaverGone(f"the checkpoint save helper could not start: {why}")
            self._ready = True

    def has_message(self) -> bool:
        """Whether an outcome can be received without waiting."""
        if not select.select([self._sock], [], [], 0)[0]:
            return False
        if self._ready:
            return True
        self.wait_ready()  # what arrived was the helper's "ready"
        return self.has_message()

    def receive(self) -> object:
        """The outcome of the oldest save sent and not yet received (its slot is free again)."""
        self.wait_ready()
        outcome = self._receive()
        self._free.append(self._busy.popleft())
        return outcome

    def _receive(self) -> object:
        try:
            received = receive(self._sock)
        except OSError:
            received = None
        if received is None:
            raise SaverGone("the checkpoint save helper is gone (it died)")
        return received[0]

    def close(self) -> None:
        """Let the helper finish what it was sent and end (it ends when the socket closes)."""
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_WR)
        if self._proc is not None:
            try:
                self._proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
        if self._thread is not None:
            self._thread.join(timeout=60)
        self._sock.close()
        for slot in (*self._free, *self._busy):
            slot.close()
        self._free.clear()
        self._busy.clear()


def helper_main(fd: int, parent: int) -> None:
    """Entry point of the helper process (already at idle priority)."""
    if sys.platform == "linux":
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the rank died before the line above
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a stop request is for the rank, which then closes the socket
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    torch.set_num_threads(1)
    serve(socket.socket(fileno=fd))


def serve(sock: socket.socket) -> None:
    """Run saves from ``sock`` until the rank closes it; reply to each with its agreed outcome."""
    (config, info, prefix), _ = receive(sock)
    try:
        saver = Saver(config, info, prefix)
    except Exception as exc:
        send(sock, ("error", f"{type(exc).__name__}: {exc}"))
        sock.close()
        return
    send(sock, ("ready", None))
    with contextlib.closing(sock):
        while (received := receive(sock)) is not None:
            (step, files, *rest), memory = received
            files = {name: placed_tensors(packed, memory) for name, packed in files.items()}
            try:
                outcome = saver.save(step, files, *rest)
            except Exception as exc:  # the meeting failed (a peer's helper died, the store went away): not committed
                outcome = ("failed", step, f"rank {info.rank}: {type(exc).__name__}: {exc}")
            send(sock, outcome)  # the rank reuses the slot once it has this: the save no longer reads it


def log(message: str) -> None:
    print(f"[ftrain] {message}", flush=True)


def _store_prefix() -> str:
    """Keys of the helpers in torchrun's store: apart from the ranks' own, and from an earlier restart's."""
    return f"ftrain-saver/{os.environ.get('TORCHELASTIC_RUN_ID', '')}/{os.environ.get('TORCHELASTIC_RESTART_COUNT', 0)}"
