"""One torchrun launch and every process it started: finding, signalling and blaming them."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import threading
import time

from ftrain.heartbeat import TOKEN_ENV
from ftrain.supervise import procfs
from ftrain.supervise.coordinator import Plan

POLL = 0.1


def torchrun_command(nproc_per_node: int, rendezvous: list[str], module: str, train_args: list[str]) -> list[str]:
    """One attempt: torchrun without restarts of its own (the supervisor owns the restart policy)."""
    return [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--max-restarts=0",
        f"--nproc-per-node={nproc_per_node}",
        *rendezvous,
        "-m",
        module,
        "train",
        *train_args,
    ]


def processes_with(token: str) -> list[int]:
    """Live processes whose environment carries this attempt's token (zombies have no readable environment)."""
    needle = f"{TOKEN_ENV}={token}".encode()
    return [pid for pid in procfs.pids() if needle in procfs.read(pid, "environ").split(b"\0")]


def signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


class Attempt:
    """One torchrun launch and every process it started; copies torchrun's stderr and reads its failure report."""

    def __init__(self, plan: Plan, command: list[str], env: dict[str, str], token: str) -> None:
        self.plan = plan
        self.token = token
        self.proc = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, start_new_session=True)
        self.failures: dict[int, int] = {}
        """Global rank -> exit code of every failed worker, from torchrun's ChildFailedError report."""
        self.dead: list[int] = []
        """Ranks the supervisor saw die mid-training."""
        self.killed: set[int] = set()
        """Ranks the supervisor then SIGKILLed: doomed by the dead ones."""
        self.completed = 0
        self.committed: int | None = None
        self.resumed: int | None = None
        self.progressed = False
        self.seen = False
        self.reported = False
        self._copier = threading.Thread(target=self._copy_stderr, daemon=True)
        self._copier.start()

    def _copy_stderr(self) -> None:
        in_report, rank = False, None
        for raw in self.proc.stderr:
            line = raw.decode(errors="replace")
            sys.stderr.write(line)
            sys.stderr.flush()
            if line.startswith("Failures:"):
                in_report = True
            elif in_report and (match := re.match(r"\s*rank\s*:\s*(\d+)", line)):
                rank = int(match[1])
            elif in_report and rank is not None and (match := re.match(r"\s*exitcode\s*:\s*(-?\d+)", line)):
                self.failures[rank] = int(match[1])

    def culprit(self) -> tuple[int, int] | None:
        """(rank, exit code) to blame. Ranks the supervisor killed do not count. Of the others, a rank killed by a
        signal comes first (someone killed it; the rest then failed on the broken group), then a specific exit code
        before 1 (what a broken group gives) or SIGTERM (what torchrun sends the survivors), then the lowest rank.
        torchrun's own root cause is only the first failure it noticed, arbitrary when several die within a poll."""
        own = {rank: code for rank, code in self.failures.items() if rank not in self.killed} or self.failures

        def order(item: tuple[int, int]) -> tuple[bool, bool, int]:
            rank, code = item
            return (not (code < 0 and code != -signal.SIGTERM), code in (1, -signal.SIGTERM), rank)

        return min(own.items(), key=order) if own else None

    def terminate(self) -> None:
        """SIGTERM every worker (each saves at the next iteration boundary), or torchrun before it has any."""
        for pid in self.workers() or ([self.proc.pid] if self.proc.poll() is None else []):
            kill(pid, signal.SIGTERM)

    def workers(self) -> list[int]:
        return [pid for pid in processes_with(self.token) if pid != self.proc.pid]

    def stop(self, grace: float) -> None:
        """``terminate``, then SIGKILL whatever is left after ``grace`` seconds."""
        self.terminate()
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline and (self.proc.poll() is None or self.workers()):
            time.sleep(POLL)
        self.kill()

    def kill(self) -> None:
        for _ in range(100):
            pids = processes_with(self.token)
            if not pids and self.proc.poll() is not None:
                break
            for pid in pids:
                kill(pid, signal.SIGKILL)
            time.sleep(POLL)
        self._copier.join(timeout=2)

    def cause(self, code: int) -> str:
        culprit = self.culprit()
        if culprit is not None:
            rank, worker_code = culprit
            how = f"killed by {signal_name(-worker_code)}" if worker_code < 0 else f"exited with code {worker_code}"
            return f"rank {rank} {how}"
        if code < 0:
            return f"torchrun killed by {signal_name(-code)}"
        return f"torchrun exited with code {code}"


def kill(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)
