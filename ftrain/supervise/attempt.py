"""One torchrun launch and every process it started: finding, signalling and blaming them.

Every attempt has a directory of its own, ``<log_dir>/torchrun/[node-R/]attempt-N-gG`` (attempt N of generation G) (the
newest ``KEPT_LOGS`` stay), which torchrun gets as ``--log-dir``, so the workers' error files land there (see
``ftrain/errorfile.py``). ``stderr.log`` there holds everything torchrun and the workers write to stderr: none of it
reaches the console. torchrun runs as ``ftrain.torchrun``, which writes torchrun's own account of the failed
workers (exit code and recorded error of each) to ``failures.json`` instead of a traceback and a text report.

Train arguments that carry credentials (storage URL, storage options) reach the workers through their environment,
redacted on their command lines, which every user of the machine reads (``redact.hide_credentials``). No process of
an attempt outlives the supervisor, however it ends (``ftrain/lifeline.py``: torchrun dies with it, each worker
watches it).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from ftrain import errorfile, procfs
from ftrain.errors import STOPPED
from ftrain.heartbeat import ENV_DIR, NODE_ENV, STOP_FILE, TOKEN_ENV, read_heartbeats
from ftrain.lifeline import SUPERVISOR_ENV, supervisor_env
from ftrain.proctitle import AGENT, title
from ftrain.supervise.auth import SECRET_ENV
from ftrain.supervise.options import SupervisorOptions, Workers, parse_workers
from ftrain.supervise.outcome import FINAL_FIRST, WorkerFailure, blame
from ftrain.supervise.plan import Plan
from ftrain.warm import LISTENER_ENV, POOL_ENV, address

POLL = 0.1
UNDEAD_LINE = 30.0
"""Seconds between two lines about a process that outlives its SIGKILL."""
TORCHRUN = "ftrain.torchrun"
"""torchrun, in a process of its own (the module imports torch: the supervisor only names it)."""
WARM = "ftrain.warm"
"""The warm pool and torchrun's stand-in (``python -m ftrain.warm serve | torchrun ...``)."""
WORKER_MODULE_ENV = "FTRAIN_WORKER_MODULE"
"""Test hook (private): the module torchrun runs (``-m MODULE train ...``, default ``ftrain``)."""
FAILURES = "failures.json"
OUTPUT = "stderr.log"
KEPT_LOGS = 5
"""Attempts whose directory is kept."""
AGENT_TITLE = title(AGENT).encode()
"""The title torchrun's agent gives itself, by which ``torchruns`` finds the one the warm pool forked."""


def attempt_env(
    heartbeat_dir: Path, token: str, stop_grace: float, node: int, hidden: dict[str, str]
) -> dict[str, str]:
    """The environment of torchrun and its workers: heartbeats go to ``heartbeat_dir`` (emptied of an earlier
    attempt's now), every process carries ``token`` and this ``node``'s rank, torchrun waits ``stop_grace`` for
    workers it stops, every process knows its supervisor (``ftrain/lifeline.py``: none outlives it); ``hidden``: the
    train arguments that carry credentials (see ``redact.hide_credentials``: never on a command line, which every
    user of the machine can read); the coordinator's secret stays with the supervisor.

    ``TORCH_DISABLE_SHARE_RDZV_TCP_STORE=1``: when a node joins an elastic run, torchrun's agents restart their
    workers in a larger world. With the agent's store shared with the workers (torch's default), the workers of that
    second round hang in ``init_process_group`` (torch 2.13, gloo: their keys sit under the prefix of the unchanged
    restart count 0, next to the first round's); with it off, each round's rank 0 hosts a fresh store
    (``tests/supervise/test_elastic.py`` grows a world both ways)."""
    heartbeat_dir.mkdir(parents=True, exist_ok=True)
    for stale in [*heartbeat_dir.glob("rank-*"), *heartbeat_dir.glob(".*.tmp"), heartbeat_dir / STOP_FILE]:
        stale.unlink(missing_ok=True)
    return {
        **_inherited(),
        ENV_DIR: str(heartbeat_dir),
        TOKEN_ENV: token,
        NODE_ENV: str(node),
        "TORCH_DISABLE_SHARE_RDZV_TCP_STORE": os.environ.get("TORCH_DISABLE_SHARE_RDZV_TCP_STORE", "1"),
        "TORCH_ELASTIC_SHUTDOWN_TIMEOUT": str(math.ceil(stop_grace)),
        **hidden,
    }


def _inherited() -> dict[str, str]:
    """The supervisor's environment but its secret (the workers do not need it), naming it as their supervisor."""
    return {**{name: value for name, value in os.environ.items() if name != SECRET_ENV}, **supervisor_env()}


class Launcher:
    """How this node starts its attempts: warm (torchrun and its workers forked from this node's pool, ``ftrain/warm``,
    started here) or cold. A test's own worker module (``WORKER_MODULE_ENV``) starts cold: the pool preloads ftrain's.
    """

    def __init__(self, options: SupervisorOptions, log: Path) -> None:
        """``log``: the pool's output."""
        self.nproc_per_node = options.nproc_per_node
        self.module = os.environ.get(WORKER_MODULE_ENV, "ftrain")
        self.secret = secrets.token_hex(16)
        warm = parse_workers(options.workers) is Workers.WARM and self.module == "ftrain"
        self.pool = self._start_pool(log) if warm else None

    def command(self, rendezvous: list[str], train_args: list[str], log_dir: Path) -> tuple[list[str], dict[str, str]]:
        """One attempt: torchrun without restarts of its own (the supervisor owns the restart policy), and what its
        environment adds for a warm start."""
        if self.pool is not None and self.pool.poll() is not None:
            print(f"ftrain supervise: the warm pool ended (exit {self.pool.returncode}): cold starts", file=sys.stderr)
            self.pool = None
        command = [
            sys.executable,
            "-m",
            *([WARM, "torchrun"] if self.pool else [TORCHRUN]),
            f"--failures={log_dir / FAILURES}",
            "--max-restarts=0",
            f"--nproc-per-node={self.nproc_per_node}",
            f"--log-dir={log_dir}",
            *rendezvous,
            "-m",
            self.module,
            "train",
            *train_args,
        ]
        return command, {POOL_ENV: self.secret} if self.pool else {}

    def close(self) -> None:
        if self.pool is not None:
            self.pool.kill()
            self.pool.wait()

    def _start_pool(self, log: Path) -> subprocess.Popen | None:
        """The pool on a socket bound here (none, with a line, where its name is taken). Its environment is the
        workers' as far as it is known before torchrun: imports that read one (OpenMP's thread count: torchrun's 1 for
        several workers a node) see what a cold worker's do."""
        env = _inherited()
        listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            listener.bind(address(env[SUPERVISOR_ENV]))
            listener.listen(64)
        except (OSError, KeyError) as error:  # KeyError: no /proc to name this supervisor by
            listener.close()
            print(f"ftrain supervise: no warm pool ({error}): cold starts", file=sys.stderr)
            return None
        env[LISTENER_ENV] = f"{listener.fileno()}:{self.secret}"
        if self.nproc_per_node > 1:
            env.setdefault("OMP_NUM_THREADS", "1")
        log.parent.mkdir(parents=True, exist_ok=True)
        with listener, log.open("ab") as output:
            command = [sys.executable, "-u", "-m", WARM, "serve"]
            return subprocess.Popen(
                command,
                env=env,
                stdout=output,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                pass_fds=[listener.fileno()],
            )


def new_log_dir(root: Path, plan: Plan) -> Path:
    """A fresh directory for the logs of ``plan``'s attempt under ``root``; older ones beyond ``KEPT_LOGS`` go."""
    root.mkdir(parents=True, exist_ok=True)
    old = sorted(root.iterdir(), key=lambda path: path.stat().st_mtime)
    for stale in old[: max(0, len(old) - KEPT_LOGS + 1)]:
        shutil.rmtree(stale, ignore_errors=True)
    path = root / f"attempt-{plan.attempt}-g{plan.generation}"
    path.mkdir(exist_ok=True)
    return path


def processes_with(token: str) -> list[int]:
    """Live processes whose environment carries this attempt's token (zombies have no readable environment)."""
    return procfs.with_environment(TOKEN_ENV, token)


def signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


class Attempt:
    """One torchrun launch and every process it started; its stderr goes to ``log_dir``, and so does torchrun's
    account of the workers that failed."""

    def __init__(
        self,
        plan: Plan,
        command: list[str],
        env: dict[str, str],
        token: str,
        log_dir: Path,
        say=print,
        stopping=lambda: False,
    ) -> None:
        """``say``, ``stopping``: see ``kill``."""
        self.plan = plan
        self.say, self.stopping = say, stopping
        self.token = token
        self.log_dir = log_dir
        self.heartbeat_dir = env.get(ENV_DIR)
        with (log_dir / OUTPUT).open("ab") as output:
            self.proc = subprocess.Popen(command, env=env, stderr=output, start_new_session=True)
        self.failures: dict[int, WorkerFailure] = {}
        """Global rank -> how each failed worker ended, as torchrun saw it (read once every process is gone)."""
        self.dead: list[int] = []
        """Ranks the supervisor saw die mid-training."""
        self.killed: set[int] = set()
        """Ranks the supervisor then SIGKILLed: doomed by the dead ones."""
        self.torchrun_stopped: float | None = None
        """Since when torchrun has been seen stopped with no worker left (``Supervisor._torchrun_stopped``)."""
        self.completed = 0
        self.committed: int | None = None
        self.resumed: int | None = None
        self.started = False
        """Whether a worker of it was seen to have restored its start (a step, or none for a fresh one)."""
        self.started_from: int | None = None
        """The step its first worker group resumed from (a regroup inside it resumes from its own commits)."""
        self.progressed = False
        self.seen = False
        self.world: int | None = None
        """World size of the worker group the ledger follows (torchrun may restart it in a larger world)."""
        self.reported = False

    def note_start(self, step: int | None) -> None:
        """``started_from``, the first time a worker tells where it started."""
        if not self.started:
            self.started, self.started_from = True, step

    def culprit(self) -> tuple[int, WorkerFailure] | None:
        """The rank to blame and how it ended (see ``outcome.blame``)."""
        return blame(self.failures, self.killed)

    def terminate(self, signum: int = signal.SIGTERM) -> None:
        """SIGTERM every worker (each saves at the next iteration boundary), or torchrun before it has any; SIGHUP
        where the supervisor got one: a stop alike, and the workers print no more to the terminal that closed."""
        for pid in self.workers() or ([self.proc.pid] if self.proc.poll() is None else []):
            kill(pid, signum)

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
        """SIGKILL every process of the attempt until none is left, so that the next attempt never runs beside one
        of them (a rank 0 that would commit over the shards the next one's start clears). Found by the token in
        their environment, and the workers also by their heartbeats: a warm worker's environment is its pool's. One
        that outlives its SIGKILL (asleep in the kernel, e.g. on a hung network filesystem) is waited for, with a
        line through ``self.say`` every ``UNDEAD_LINE`` seconds; past the first, not if ``self.stopping()`` (the
        supervisor ends)."""
        started = told = time.monotonic()
        while (pids := self.processes()) or self.proc.poll() is None:
            for pid in pids:
                kill(pid, signal.SIGKILL)
            if pids and time.monotonic() - told >= UNDEAD_LINE:
                told, states = time.monotonic(), ", ".join(f"{pid} ({procfs.state(pid)})" for pid in pids)
                self.say(
                    f"attempt {self.plan.attempt}: process {states} still alive {told - started:.0f} s after SIGKILL; "
                    "the next attempt waits for it"
                )
            if self.stopping() and time.monotonic() - started >= UNDEAD_LINE:
                break  # the supervisor ends: no next attempt to keep from it
            time.sleep(POLL)
        self._read_failures()

    def torchruns(self) -> list[int]:
        """torchrun's processes: the one launched (the agent, or its warm stand-in) and the agent the warm pool forked
        for it, in the supervisor's tree by its title."""
        forked = [pid for pid in procfs.descendants(os.getpid()) if procfs.read(pid, "cmdline").startswith(AGENT_TITLE)]
        return sorted({self.proc.pid, *forked})

    def stopped_torchrun(self) -> int | None:
        """A torchrun process of the attempt that is stopped (T) while no other process of it is left, else None."""
        torchruns = self.torchruns()
        stopped = next((pid for pid in torchruns if procfs.state(pid) in ("T", "t")), None)
        return None if stopped is None or set(self.processes()) - set(torchruns) else stopped

    def processes(self) -> list[int]:
        """The live processes of the attempt (see ``kill``); a heartbeat's pid counts while it is still a worker's
        (its short name, ``ftrain-rRofW-...``: the pid may have been handed out again) and not a zombie."""
        workers = [beat.pid for beat in read_heartbeats(self.heartbeat_dir).values()] if self.heartbeat_dir else []
        mine = [pid for pid in workers if procfs.read(pid, "comm").startswith(b"ftrain-r") and procfs.state(pid) != "Z"]
        return sorted({*processes_with(self.token), *mine} - {os.getpid()})

    def _read_failures(self) -> None:
        try:
            failures = json.loads((self.log_dir / FAILURES).read_text())
        except (OSError, ValueError):
            return  # no worker failed, or torchrun itself died
        self.failures = {
            int(rank): WorkerFailure(
                failure["exitcode"], errorfile.message(failure["error"]), errorfile.recorded_at(failure["error"])
            )
            for rank, failure in failures.items()
        }

    def exit_fields(self, cause: str, phases: set[str]) -> dict:
        """What the ``exit`` event records: the attempt, torchrun's code, the ``cause``, each failed rank's code and
        error, and the final heartbeat ``phases``."""
        return {
            "attempt": self.plan.attempt,
            "code": self.proc.returncode,
            "cause": cause,
            "failures": {str(rank): failure.code for rank, failure in sorted(self.failures.items())},
            "errors": {str(rank): failure.error for rank, failure in sorted(self.failures.items()) if failure.error},
            "phases": sorted(phases),
        }

    def cause(self, code: int) -> str:
        """What ended the attempt, in one line: the worker to blame and what it recorded, else torchrun; where the
        output is when nothing was recorded, or when what was recorded is an error's last line (its traceback is
        there; an exit that names its cause, bad input, the storage or a stop, has none)."""
        culprit = self.culprit()
        output = self.log_dir / OUTPUT
        if culprit is not None:
            rank, failure = culprit
            if failure.code < 0:
                return f"rank {rank} killed by {signal_name(-failure.code)}"
            if failure.error is None:
                return f"rank {rank} exited with code {failure.code}: see {output}"
            traceback = f" (traceback in {output})" if failure.code not in (*FINAL_FIRST, *STOPPED) else ""
            return f"rank {rank} exited with code {failure.code}: {failure.error}{traceback}"
        if code < 0:
            return f"torchrun killed by {signal_name(-code)}"
        return f"torchrun exited with code {code}: see {output}"


def kill(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):  # gone, or (its pid handed out again) not ours
        os.kill(pid, sig)
