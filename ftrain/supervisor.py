"""``ftrain supervise``: launch torchrun, watch its workers, restart them from the newest verified checkpoint.

Stdlib only (plus the torch-free config and heartbeat modules): the supervisor launches and watches processes.

Launch. Every attempt is a new ``torchrun --max-restarts=0`` in its own session, with ``FTRAIN_HEARTBEAT_DIR``
set, and a rendezvous nothing has used before: ``--standalone`` on one node (a new TCP store on a free port);
on several nodes a static rendezvous on a new port per attempt (see "Several nodes"). torchrun's own restarts
keep one TCP store, from which restarted workers read stale gloo peer addresses; a new torchrun cannot.

Detect. Crash: torchrun exits non-zero, or is killed (its workers, each in a session of its own, are then
orphans: the supervisor finds every process of an attempt by the ``FTRAIN_ATTEMPT_TOKEN`` in its environment).
Hang: a rank's heartbeat ``seq`` does not change within the hang timeout (``auto``: max(30 s, 10 x the longest gap
seen between two heartbeats of a rank), and ``--startup-grace`` until every rank is past its ``start`` heartbeat).

Recover. A worker that died mid-training dooms the others: they get SIGKILL at once. Orphans of a killed
torchrun get SIGTERM (they agree, save, exit), then SIGKILL after ``--stop-grace``. A hung group gets SIGKILL at
once (its collectives cannot agree on a save; commits are crash-safe). Then back off (not after an attempt that
completed iterations; ``--backoff-initial`` after one that completed none, doubled for each further one, at most
``--backoff-max``) and launch again; the workers resume from the newest verified checkpoint themselves.

Preemption. SIGTERM or SIGINT to the supervisor: SIGTERM to the workers, which agree at the next iteration
boundary, save and exit 0; SIGKILL after ``--stop-grace``; a second signal kills at once. No restart.

Several nodes. The same command on every node with ``--nnodes N --node-rank R --rdzv-endpoint HOST:PORT`` where
HOST is node 0's address. Node 0's supervisor listens on PORT and names the current attempt and a fresh port for
its static rendezvous (node 0's torchrun hosts the store there). A node whose attempt fails tells node 0, which
moves everyone to the next attempt on a new port; the other nodes see that within half a second and restart too.
So no node can join the store of a dead attempt, and all nodes restart exactly once per failure.

Record. One JSON line per decision in ``<log_dir>/events.jsonl``: ``start``, ``resumed``, ``worker_died``,
``exit``, ``hang``, ``superseded``, ``restart``, ``recovered``, ``preempt``, and the ending (``done``,
``preempted``, ``crash_loop``, ``max_restarts``, ``usage``, ``peer_lost``, ``peer_ended``), then ``summary``
(restarts, iterations lost, downtime).

Exit codes:

- 0: training finished.
- 2: bad input (config or options, or a worker exited with 2); nothing is restarted.
- 3: crash loop: ``--crash-loop`` restarts in a row committed no new checkpoint.
- 4: ``--max-restarts`` exhausted.
- 5: several nodes: node 0's supervisor was unreachable for ``--rdzv-timeout`` seconds.
- 143: preempted (SIGTERM/SIGINT): the workers saved; run the same command again to continue. 128 + SIGTERM,
  so schedulers that retry signal exits (e.g. Kubernetes' ``ExitCode`` restart policy) run it again.

Test hook (private): ``FTRAIN_WORKER_MODULE`` names the module torchrun runs as ``-m MODULE train ...`` (default
``ftrain``), so the tests can supervise a small stand-in that speaks the heartbeat protocol.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import re
import secrets
import signal
import socket
import socketserver
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from ftrain import procfs
from ftrain.config import load_config
from ftrain.errors import EXIT_USAGE, UserError
from ftrain.heartbeat import ENV_DIR, TOKEN_ENV, Heartbeat, read_heartbeats

EXIT_DONE = 0
EXIT_CRASH_LOOP = 3
EXIT_MAX_RESTARTS = 4
EXIT_PEER_LOST = 5
EXIT_PREEMPTED = 128 + signal.SIGTERM

WORKER_MODULE_ENV = "FTRAIN_WORKER_MODULE"

POLL = 0.1
"""Seconds between two looks at torchrun and the heartbeats."""
PEER_POLL = 0.5
"""Seconds between two questions to node 0 while an attempt runs."""
HANG_FLOOR = 30.0
HANG_FACTOR = 10.0
LINGER = 30.0
"""Seconds node 0 keeps answering after the end, until every node has learnt the outcome."""
QUIET_PHASES = ("done", "preempted")
"""Phases after which a rank only exits: never a hang."""


@dataclass
class SupervisorOptions:
    nproc_per_node: int = field(default=1, metadata={"help": "worker processes on this node"})
    nnodes: str = field(default="1", metadata={"help": "number of nodes; run the same command on every node"})
    node_rank: int = field(default=0, metadata={"help": "this node's rank, 0 .. nnodes-1 (node 0 coordinates)"})
    rdzv_endpoint: str = field(
        default="", metadata={"help": "several nodes: HOST:PORT, node 0's address and a free port for its supervisor"}
    )
    rdzv_timeout: float = field(
        default=600.0, metadata={"help": "several nodes: seconds to wait for the other nodes (then exit 5)"}
    )
    max_restarts: int = field(default=10, metadata={"help": "restarts before giving up (exit 4)"})
    hang_timeout: str = field(
        default="auto",
        metadata={"help": "seconds without a heartbeat before a rank counts as hung, or auto (from observed gaps)"},
    )
    startup_grace: float = field(
        default=300.0, metadata={"help": "seconds an attempt may take to reach its first iteration on every rank"}
    )
    backoff_initial: float = field(
        default=1.0,
        metadata={"help": "seconds before restarting an attempt that completed no iteration (doubles each time)"},
    )
    backoff_max: float = field(default=60.0, metadata={"help": "longest back-off in seconds"})
    crash_loop: int = field(
        default=3, metadata={"help": "stop (exit 3) after this many restarts in a row commit no new step (0: never)"}
    )
    stop_grace: float = field(
        default=30.0, metadata={"help": "seconds between SIGTERM and SIGKILL when stopping workers (time to save)"}
    )


def supervise(options: SupervisorOptions, config_path: str, storage: str | None, overrides: list[str]) -> int:
    """Run training under supervision until it finishes or gives up; returns the exit code (see module doc)."""
    config = load_config(config_path, overrides, storage)
    hang_timeout = _parse_hang_timeout(options.hang_timeout)
    nnodes, endpoint = _parse_nodes(options)
    train_args = [config_path, *(["--storage", storage] if storage is not None else []), *overrides]
    supervisor = Supervisor(options, nnodes, endpoint, Path(config.log_dir), hang_timeout, train_args)
    previous = {sig: signal.signal(sig, supervisor.on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        return supervisor.run()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        supervisor.close()


def _parse_hang_timeout(value: str) -> float | None:
    if value == "auto":
        return None
    try:
        seconds = float(value)
    except ValueError:
        seconds = -1.0
    if not seconds > 0:
        raise UserError(f"--hang-timeout={value!r} must be auto or a positive number of seconds")
    return seconds


def _parse_nodes(options: SupervisorOptions) -> tuple[int, tuple[str, int] | None]:
    """The number of nodes, and node 0's ``(host, port)`` when there are several."""
    if not options.nnodes.isdigit() or int(options.nnodes) < 1:
        raise UserError(f"--nnodes={options.nnodes!r} must be a number of nodes (elastic MIN:MAX is not supported)")
    nnodes = int(options.nnodes)
    if options.nproc_per_node < 1:
        raise UserError(f"--nproc-per-node={options.nproc_per_node} must be at least 1")
    if nnodes == 1:
        return nnodes, None
    if not 0 <= options.node_rank < nnodes:
        raise UserError(f"--node-rank={options.node_rank} must be between 0 and {nnodes - 1}")
    host, _, port = options.rdzv_endpoint.rpartition(":")
    if not host or not port.isdigit():
        raise UserError("several nodes need --rdzv-endpoint=HOST:PORT, node 0's address and a free port")
    return nnodes, (host, int(port))


@dataclass
class Plan:
    """The attempt every node runs now, as node 0 decides; ``final`` is set once the run has ended."""

    token: str
    attempt: int
    port: int | None
    final: int | None = None


class Coordinator:
    """Node 0's record of the current attempt. On one node it is just the attempt counter.

    A failed attempt moves the plan to the next attempt and a new rendezvous port (only the first report of
    a failure counts); ``finish`` publishes the exit code that ends the run on every node.
    """

    def __init__(self, multi_node: bool) -> None:
        self._multi_node = multi_node
        self._lock = threading.Lock()
        self._plan = Plan(secrets.token_hex(4), 0, self._port())
        self._informed: set[int] = set()

    def _port(self) -> int | None:
        return _free_port() if self._multi_node else None

    def handle(self, request: dict) -> dict:
        with self._lock:
            plan = self._plan
            current = request.get("token") == plan.token and request.get("attempt") == plan.attempt
            if request["op"] == "fail" and current and plan.final is None:
                self._plan = plan = Plan(plan.token, plan.attempt + 1, self._port())
            elif request["op"] == "finish" and plan.final is None:
                plan.final = request["code"]
            if plan.final is not None:
                self._informed.add(request["node"])
            return dataclasses.asdict(plan)

    def serve(self, port: int) -> socketserver.TCPServer:
        try:
            server = _Server(("", port), _Handler)
        except OSError as error:
            raise UserError(
                f"--rdzv-endpoint: cannot listen on port {port} ({error.strerror}): pick a free port"
            ) from None
        server.coordinator = self
        threading.Thread(target=server.serve_forever, args=(POLL,), daemon=True).start()
        return server

    def wait_informed(self, nnodes: int, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if self._informed >= set(range(nnodes)):
                    return
            time.sleep(POLL)


class _Server(socketserver.ThreadingTCPServer):
    allow_reuse_address = True
    daemon_threads = True
    coordinator: Coordinator


class _Handler(socketserver.StreamRequestHandler):
    def handle(self) -> None:
        try:
            reply = self.server.coordinator.handle(json.loads(self.rfile.readline()))
        except (ValueError, KeyError, TypeError, AttributeError):
            return  # not one of ours
        self.wfile.write(json.dumps(reply).encode() + b"\n")


class Link:
    """This node's line to the coordinator: a direct call on node 0, one TCP request per question elsewhere."""

    def __init__(self, node: int, coordinator: Coordinator | None, address: tuple[str, int] | None) -> None:
        self.node = node
        self.coordinator = coordinator
        self.address = address

    def ask(self, op: str, **fields) -> Plan:
        """Raises OSError when node 0 cannot be reached."""
        request = {"op": op, "node": self.node, **fields}
        if self.coordinator is not None:
            return Plan(**self.coordinator.handle(request))
        with socket.create_connection(self.address, timeout=5) as conn:
            conn.sendall(json.dumps(request).encode() + b"\n")
            reply = conn.makefile("rb").readline()
        if not reply:
            raise ConnectionError("node 0 closed the connection")
        return Plan(**json.loads(reply))


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("", 0))
        return sock.getsockname()[1]


class EventLog:
    """Appends one JSON line per decision; decisions with a message are also printed."""

    def __init__(self, path: Path, node: int | None) -> None:
        self.path = path
        self.node = node
        path.parent.mkdir(parents=True, exist_ok=True)

    def __call__(self, event: str, message: str = "", **fields) -> None:
        record = {"time": round(time.time(), 3), "event": event, **fields}
        if self.node is not None:
            record["node"] = self.node
        with self.path.open("a") as file:
            file.write(json.dumps(record) + "\n")
        if message:
            print(f"ftrain supervise: {message}", file=sys.stderr, flush=True)


class HangWatch:
    """Times every rank's heartbeat ``seq``; when one has been silent too long, names the hung rank: a stopped
    (T) or uninterruptible (D) process if there is one, else the rank silent longest."""

    def __init__(self, timeout: float | None, startup_grace: float, ranks: int) -> None:
        self.timeout = timeout
        self.startup_grace = startup_grace
        self.ranks = ranks
        self.longest = 0.0
        """Longest gap seen between two heartbeats of a rank after start-up, over all attempts."""

    def restart(self, now: float) -> None:
        self.launched = now
        self.started = False
        self.changed: dict[int, tuple[int, float]] = {}

    def limit(self) -> float:
        if self.timeout is not None:
            return self.timeout
        return max(HANG_FLOOR, HANG_FACTOR * self.longest)

    def check(self, beats: dict[int, Heartbeat], now: float) -> Hang | None:
        """Record progress in ``beats``; return the hang if there is one."""
        for rank, beat in beats.items():
            seq, since = self.changed.get(rank, (None, now))
            if beat.seq != seq:
                if self.started and seq is not None:
                    self.longest = max(self.longest, now - since)
                self.changed[rank] = (beat.seq, now)
        if not self.started:
            self.started = len(beats) >= self.ranks and all(b.phase != "start" for b in beats.values())
        if not self.started:
            if now - self.launched <= self.startup_grace:
                return None
            starting = [rank for rank, beat in beats.items() if beat.phase == "start"]
            rank = min(starting) if starting else None
            return Hang(rank, "start", round(now - self.launched, 1), self.startup_grace, ranks_seen=len(beats))
        active = [(self.changed[rank][1], rank) for rank, beat in beats.items() if beat.phase not in QUIET_PHASES]
        if not active:
            return None
        since, rank = min(active)
        if now - since <= self.limit():
            return None
        states = {r: _process_state(b.pid) for r, b in sorted(beats.items())}
        # the others wait for it in a collective and may have been silent longer: name a stopped rank if any
        rank = next((r for r, state in states.items() if state in ("T", "t", "D")), rank)
        beat = beats[rank]
        seconds, limit = round(now - self.changed[rank][1], 1), round(self.limit(), 1)
        processes = {str(r): state for r, state in states.items()}
        return Hang(rank, beat.phase, seconds, limit, iteration=beat.iteration, processes=processes)


@dataclass
class Hang:
    """A rank silent for longer than the limit, or a start-up that took longer than the grace (``ranks_seen`` set)."""

    rank: int | None
    phase: str
    seconds: float
    limit: float
    iteration: int | None = None
    processes: dict[str, str] | None = None
    """Each rank's process state letter: a stopped (T) or uninterruptible (D) one is named as the hung rank."""
    ranks_seen: int | None = None

    def fields(self) -> dict:
        """For the event log: the fields that apply (``rank`` always, None if no rank was to blame)."""
        return {key: value for key, value in dataclasses.asdict(self).items() if value is not None or key == "rank"}

    def cause(self) -> str:
        return "killed: start-up hung" if self.ranks_seen is not None else f"killed: rank {self.rank} hung"

    def describe(self) -> str:
        if self.ranks_seen is not None:
            return f"not every rank got past start-up within {self.limit:g} s (--startup-grace)"
        return f"rank {self.rank} silent for {self.seconds} s in phase {self.phase} (limit {self.limit} s)"


def _process_state(pid: int) -> str:
    """The kernel's state letter for ``pid`` (R running, S sleeping, T stopped, ...), or ``gone``."""
    fields = procfs.stat_fields(pid)
    return fields[0] if fields else "gone"


def _processes_with(token: str) -> list[int]:
    """Live processes whose environment carries this attempt's token (zombies have no readable environment)."""
    needle = f"{TOKEN_ENV}={token}".encode()
    return [pid for pid in procfs.pids() if needle in procfs.read(pid, "environ").split(b"\0")]


def _signal_name(number: int) -> str:
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
            _kill(pid, signal.SIGTERM)

    def workers(self) -> list[int]:
        return [pid for pid in _processes_with(self.token) if pid != self.proc.pid]

    def stop(self, grace: float) -> None:
        """``terminate``, then SIGKILL whatever is left after ``grace`` seconds."""
        self.terminate()
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline and (self.proc.poll() is None or self.workers()):
            time.sleep(POLL)
        self.kill()

    def kill(self) -> None:
        for _ in range(100):
            pids = _processes_with(self.token)
            if not pids and self.proc.poll() is not None:
                break
            for pid in pids:
                _kill(pid, signal.SIGKILL)
            time.sleep(POLL)
        self._copier.join(timeout=2)

    def cause(self, code: int) -> str:
        culprit = self.culprit()
        if culprit is not None:
            rank, worker_code = culprit
            how = f"killed by {_signal_name(-worker_code)}" if worker_code < 0 else f"exited with code {worker_code}"
            return f"rank {rank} {how}"
        if code < 0:
            return f"torchrun killed by {_signal_name(-code)}"
        return f"torchrun exited with code {code}"


def _kill(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)


@dataclass
class Outcome:
    """How an attempt ended: ``failed`` (restart) or one of the endings, with its exit code and event name."""

    event: str
    code: int | None
    message: str

    @property
    def failed(self) -> bool:
        return self.event == "failed"


@dataclass
class Failure:
    """A failure not yet recovered from: when it was detected and how many iterations had completed."""

    detected: float
    completed: int


class _Stop(Exception):
    def __init__(self, event: str, code: int, message: str) -> None:
        super().__init__(message)
        self.event, self.code, self.message = event, code, message


class Supervisor:
    def __init__(
        self,
        options: SupervisorOptions,
        nnodes: int,
        endpoint: tuple[str, int] | None,
        log_dir: Path,
        hang_timeout: float | None,
        train_args: list[str],
    ) -> None:
        """``endpoint``: node 0's ``(host, port)`` when there are several nodes."""
        self.options = options
        self.nnodes = nnodes
        self.train_args = train_args
        multi = nnodes > 1
        self.heartbeat_dir = (log_dir / "heartbeat" / (f"node-{options.node_rank}" if multi else "")).resolve()
        self.events = EventLog(log_dir / "events.jsonl", options.node_rank if multi else None)
        self.hangs = HangWatch(hang_timeout, options.startup_grace, options.nproc_per_node)
        self.endpoint = endpoint
        self.coordinator = Coordinator(multi) if options.node_rank == 0 or not multi else None
        self.server = self.coordinator.serve(endpoint[1]) if multi and self.coordinator else None
        self.link = Link(options.node_rank, self.coordinator, endpoint)
        self.signals: list[int] = []
        self.restarts = 0
        self.lost = 0
        self.downtime = 0.0
        self.best_committed: int | None = None
        self.failure: Failure | None = None

    def on_signal(self, number: int, frame: object) -> None:
        self.signals.append(number)

    def close(self) -> None:
        if self.server is not None:
            self.server.shutdown()
            self.server.server_close()

    def run(self) -> int:
        try:
            self._loop()
        except _Stop as stop:
            return self._end(stop.event, stop.code, stop.message)
        raise AssertionError("the supervision loop only ends by _Stop")

    def _loop(self) -> None:
        plan = self._next_plan(None)
        no_commit = no_progress = 0
        while True:
            attempt = self._launch(plan)
            outcome = self._watch(attempt)
            if not outcome.failed:
                raise _Stop(outcome.event, outcome.code, outcome.message)
            new_commit = attempt.committed is not None and (
                self.best_committed is None or attempt.committed > self.best_committed
            )
            if attempt.committed is not None:
                self.best_committed = max(attempt.committed, self.best_committed or 0)
            no_commit = 0 if new_commit or self.restarts == 0 else no_commit + 1
            no_progress = 0 if attempt.progressed else no_progress + 1
            if self.restarts >= self.options.max_restarts:
                raise _Stop("max_restarts", EXIT_MAX_RESTARTS, f"giving up after {self.restarts} restarts")
            if self.options.crash_loop and no_commit >= self.options.crash_loop:
                step = self.best_committed
                raise _Stop(
                    "crash_loop",
                    EXIT_CRASH_LOOP,
                    f"crash loop: {no_commit} restarts in a row committed no new checkpoint (newest: step {step}); "
                    "fix the cause above and run the same command again",
                )
            delay = (
                min(self.options.backoff_max, self.options.backoff_initial * 2 ** (no_progress - 1))
                if no_progress
                else 0.0
            )
            self._sleep(delay)
            plan = self._next_plan(plan)
            self.restarts += 1
            self.events(
                "restart",
                f"restart {self.restarts} (attempt {plan.attempt}) after {delay:.1f} s back-off",
                attempt=plan.attempt,
                restarts=self.restarts,
                backoff=round(delay, 2),
            )

    def _sleep(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self._raise_if_signalled()
            time.sleep(min(POLL, max(0.0, deadline - time.monotonic())))
        self._raise_if_signalled()

    def _raise_if_signalled(self) -> None:
        if self.signals:
            self.events("preempt", signal=_signal_name(self.signals[0]))
            raise _Stop("preempted", EXIT_PREEMPTED, "stopped by a signal while no workers ran; rerun to continue")

    def _next_plan(self, previous: Plan | None) -> Plan:
        """The next attempt to run (on several nodes: wait until node 0 has moved on from ``previous``)."""
        deadline = time.monotonic() + self.options.rdzv_timeout
        waiting = False
        while True:
            self._raise_if_signalled()
            try:
                plan = self.link.ask("plan")
            except OSError as error:
                plan = None
                if not waiting:
                    waiting = True
                    timeout = self.options.rdzv_timeout
                    message = f"waiting up to {timeout:g} s for node 0 at {self.options.rdzv_endpoint} ({error})"
                    print(f"ftrain supervise: {message}", file=sys.stderr, flush=True)
            if plan is not None and plan.final is not None:
                raise _Stop("peer_ended", plan.final, f"another node ended the run with exit code {plan.final}")
            if plan is not None and (previous is None or _key(plan) != _key(previous)):
                return plan
            if time.monotonic() > deadline:
                raise _Stop("peer_lost", EXIT_PEER_LOST, f"node 0 at {self.options.rdzv_endpoint} did not answer")
            time.sleep(PEER_POLL / 5)

    def _launch(self, plan: Plan) -> Attempt:
        self.heartbeat_dir.mkdir(parents=True, exist_ok=True)
        for stale in self.heartbeat_dir.glob("rank-*"):
            stale.unlink(missing_ok=True)
        token = f"{os.getpid()}-{plan.token}-{plan.attempt}"
        env = {
            **os.environ,
            ENV_DIR: str(self.heartbeat_dir),
            TOKEN_ENV: token,
            "TORCH_ELASTIC_SHUTDOWN_TIMEOUT": str(math.ceil(self.options.stop_grace)),
        }
        module = os.environ.get(WORKER_MODULE_ENV, "ftrain")
        command = [
            sys.executable,
            "-m",
            "torch.distributed.run",
            "--max-restarts=0",
            f"--nproc-per-node={self.options.nproc_per_node}",
            *self._rendezvous_args(plan),
            "-m",
            module,
            "train",
            *self.train_args,
        ]
        self.events("start", f"attempt {plan.attempt}: launching torchrun", attempt=plan.attempt, command=command)
        self.hangs.restart(time.monotonic())
        return Attempt(plan, command, env, token)

    def _rendezvous_args(self, plan: Plan) -> list[str]:
        if self.nnodes == 1:
            return ["--standalone"]
        return [
            f"--nnodes={self.nnodes}",
            f"--node-rank={self.options.node_rank}",
            "--rdzv-backend=static",
            f"--master-addr={self.endpoint[0]}",
            f"--master-port={plan.port}",
            f"--rdzv-id=ftrain-{plan.token}-{plan.attempt}",
            f"--rdzv-conf=timeout={math.ceil(self.options.rdzv_timeout)}",
        ]

    def _watch(self, attempt: Attempt) -> Outcome:
        preempt_deadline = None
        next_peer_check = time.monotonic() + PEER_POLL
        while True:
            time.sleep(POLL)
            now = time.monotonic()
            beats = read_heartbeats(self.heartbeat_dir)
            self._account(attempt, beats, now)
            code = attempt.proc.poll()
            if code is not None:
                return self._exited(attempt, code)
            if not attempt.dead:
                self._check_workers(attempt, beats)
            if self.signals and preempt_deadline is None:
                preempt_deadline = now + self.options.stop_grace
                self._preempt(attempt)
            if preempt_deadline is not None:
                if len(self.signals) > 1 or now > preempt_deadline:
                    attempt.kill()
                continue
            hang = self.hangs.check(beats, now)
            if hang is not None:
                self.events(
                    "hang",
                    f"attempt {attempt.plan.attempt}: {hang.describe()}; killing the workers",
                    attempt=attempt.plan.attempt,
                    **hang.fields(),
                )
                self._failed(attempt, now)
                attempt.kill()
                self._log_exit(attempt, hang.cause())
                return Outcome("failed", None, "hang")
            if self.nnodes > 1 and now >= next_peer_check:
                next_peer_check = now + PEER_POLL
                outcome = self._check_peers(attempt, now)
                if outcome is not None:
                    return outcome

    def _check_workers(self, attempt: Attempt, beats: dict[int, Heartbeat]) -> None:
        """A worker that died mid-training dooms the others (no collective can complete): SIGKILL them now rather
        than wait for them to fail on the broken group and for torchrun to notice (1-2 s measured here); torchrun
        still reports every exit code."""
        dead = [r for r, b in beats.items() if b.phase not in QUIET_PHASES and _process_state(b.pid) in ("gone", "Z")]
        if dead:
            latest = read_heartbeats(self.heartbeat_dir)  # a rank may have finished since we looked
            dead = [rank for rank in dead if latest.get(rank, beats[rank]).phase not in QUIET_PHASES]
        if not dead:
            return
        attempt.dead = sorted(dead)
        attempt.killed = set(beats) - set(dead)
        self.events("worker_died", attempt=attempt.plan.attempt, ranks=attempt.dead)
        for pid in attempt.workers():
            _kill(pid, signal.SIGKILL)

    def _check_peers(self, attempt: Attempt, now: float) -> Outcome | None:
        """Several nodes: stop this node's group when another node failed the attempt or ended the run."""
        try:
            plan = self.link.ask("plan")
        except OSError:
            return None
        if plan.final in (EXIT_DONE, EXIT_PREEMPTED):
            return None
        if plan.final is not None:
            attempt.stop(self.options.stop_grace)
            self._log_exit(attempt, "stopped: another node ended the run")
            return Outcome("peer_ended", plan.final, f"another node ended the run with exit code {plan.final}")
        if _key(plan) == _key(attempt.plan):
            return None
        self.events(
            "superseded",
            f"attempt {attempt.plan.attempt}: another node failed; stopping this node's workers",
            attempt=attempt.plan.attempt,
        )
        self._failed(attempt, now)
        attempt.stop(self.options.stop_grace)
        self._log_exit(attempt, "stopped: another node failed")
        return Outcome("failed", None, "superseded")

    def _preempt(self, attempt: Attempt) -> None:
        name = _signal_name(self.signals[0])
        self.events(
            "preempt",
            f"{name}: asking the workers to save and exit (SIGKILL in {self.options.stop_grace:g} s)",
            attempt=attempt.plan.attempt,
            signal=name,
        )
        if self.nnodes > 1:
            self._tell("finish", code=EXIT_PREEMPTED)
        attempt.terminate()

    def _exited(self, attempt: Attempt, code: int) -> Outcome:
        now = time.monotonic()
        orphans = attempt.workers()
        if orphans and not self.signals:
            # torchrun itself died and its workers still train. Tell the other nodes first, so that their workers'
            # coming save-and-exit reads as a restart there, not as a preemption; then let the orphans save.
            self._failed(attempt, now)
        if orphans:
            attempt.stop(self.options.stop_grace)  # ends with kill() too
        else:
            attempt.kill()
        phases = self._phases(attempt)
        cause = attempt.cause(code) if code or orphans else "exit code 0"
        outcome = self._classify(attempt, code, cause, bool(orphans), phases)
        self._log_exit(attempt, cause, f"attempt {attempt.plan.attempt}: {cause}" if outcome.failed else "", phases)
        if outcome.failed:
            self._failed(attempt, now)
        return outcome

    def _phases(self, attempt: Attempt) -> set[str]:
        """The phases of the final heartbeats (after the attempt's processes are gone)."""
        beats = read_heartbeats(self.heartbeat_dir)
        self._account(attempt, beats, time.monotonic())
        return {beat.phase for beat in beats.values()}

    def _log_exit(self, attempt: Attempt, cause: str, message: str = "", phases: set[str] | None = None) -> None:
        """The ``exit`` event; ``phases``: the final heartbeat phases, if the caller has read them already."""
        self.events(
            "exit",
            message,
            attempt=attempt.plan.attempt,
            code=attempt.proc.returncode,
            cause=cause,
            failures={str(rank): code for rank, code in sorted(attempt.failures.items())},
            phases=sorted(self._phases(attempt) if phases is None else phases),
        )

    def _classify(self, attempt: Attempt, code: int, cause: str, orphans: bool, phases: set[str]) -> Outcome:
        if self.signals:
            saved = bool(phases) and phases <= {"preempted", "done"}
            how = "the workers saved" if saved else "the workers did not all confirm a save"
            return Outcome("preempted", EXIT_PREEMPTED, f"preempted: {how} (newest step {attempt.committed})")
        if orphans:
            return Outcome("failed", None, cause)
        if code == 0 and "preempted" not in phases:
            return Outcome("done", EXIT_DONE, f"training finished (step {attempt.committed})")
        if code == 0:
            if self.nnodes > 1 and _key(self._current_plan(attempt.plan)) != _key(attempt.plan):
                return Outcome("failed", None, "stopped because another node failed")
            return Outcome(
                "preempted", EXIT_PREEMPTED, f"preempted: the workers saved step {attempt.committed}; rerun to continue"
            )
        culprit = attempt.culprit()
        if culprit is not None and culprit[1] == EXIT_USAGE:
            return Outcome("usage", EXIT_USAGE, f"{cause}: bad input (see the error above); not restarting")
        return Outcome("failed", None, cause)

    def _current_plan(self, fallback: Plan) -> Plan:
        try:
            return self.link.ask("plan")
        except OSError:
            return fallback

    def _failed(self, attempt: Attempt, now: float) -> None:
        """Once per attempt: remember the failure for the summary and tell node 0 (one node: the local counter)."""
        if attempt.reported:
            return
        attempt.reported = True
        if self.failure is None:
            self.failure = Failure(now, attempt.completed)
        else:
            self.failure.completed = max(self.failure.completed, attempt.completed)
        self._tell("fail", **_key(attempt.plan))

    def _tell(self, op: str, **fields) -> None:
        with contextlib.suppress(OSError):
            self.link.ask(op, **fields)

    def _account(self, attempt: Attempt, beats: dict[int, Heartbeat], now: float) -> None:
        """Track completed iterations and commits; log the resumed step and the first iteration after a failure."""
        if not beats:
            return
        for beat in beats.values():
            # a checkpoint/done/preempted beat keeps the iteration of the rollout; its committed step may be newer
            attempt.completed = max(attempt.completed, beat.iteration, beat.committed_step or 0)
            if beat.committed_step is not None:
                attempt.committed = max(beat.committed_step, attempt.committed or 0)
        if not attempt.seen:
            past_start = [beat for beat in beats.values() if beat.phase != "start"]  # restored by now
            if not past_start:
                return
            attempt.seen = True
            attempt.resumed = min(past_start, key=lambda beat: beat.rank).resumed_step
            self.events("resumed", attempt=attempt.plan.attempt, step=attempt.resumed)
        base = attempt.resumed or 0
        if attempt.progressed or len(beats) < self.options.nproc_per_node:
            return
        if all(beat.iteration > base for beat in beats.values()):
            attempt.progressed = True
            if self.failure is not None:
                lost = max(0, self.failure.completed - base)
                downtime = now - self.failure.detected
                self.lost += lost
                self.downtime += downtime
                self.failure = None
                self.events(
                    "recovered",
                    f"attempt {attempt.plan.attempt}: recovered from step {attempt.resumed} "
                    f"({lost} iterations lost, {downtime:.1f} s down)",
                    attempt=attempt.plan.attempt,
                    step=attempt.resumed,
                    lost=lost,
                    downtime=round(downtime, 3),
                )

    def _end(self, event: str, code: int, message: str) -> int:
        self.events(event, message, code=code)
        if self.nnodes > 1:
            self._tell("finish", code=code)
            if self.coordinator is not None:
                self.coordinator.wait_informed(self.nnodes, LINGER)
        summary = {"restarts": self.restarts, "iterations_lost": self.lost, "downtime": round(self.downtime, 2)}
        self.events(
            "summary",
            f"{event} (exit {code}): {self.restarts} restarts, {self.lost} iterations lost, "
            f"{self.downtime:.1f} s downtime",
            code=code,
            **summary,
        )
        return code


def _key(plan: Plan) -> dict:
    return {"token": plan.token, "attempt": plan.attempt}
