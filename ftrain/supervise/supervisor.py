"""``ftrain supervise``: launch torchrun, watch its workers, restart them from the newest verified checkpoint
(docs/supervision.md has the rules and the numbers).

Owns the run's state machine on this node, attempt after attempt:
- launch: a new ``torchrun --max-restarts=0`` per attempt, in its own session, on a fresh rendezvous, credentials in
  the environment only (``attempt.py``; warm: ``attempt.Launcher``; several nodes: ``link.py``);
- detect: a crash (torchrun's account of its workers: ``outcome.py``), a hang (``hang.py``), a storage that does not
  answer (exit 7: waited for, ``outage.py``), a lease lost to a newer generation (``Lease.lost``: exit 8);
- recover: SIGKILL to a doomed or hung group, SIGTERM then SIGKILL to orphans, back-off and restart
  (``restarts.py``); a worker that refused its input (exit 2) is not restarted;
- preemption: SIGTERM or SIGINT is passed on as SIGTERM (save at the next iteration boundary), exit 143 or 130 (a
  SIGINT ignored at start, a script's background job, stays ignored: ``errors.stop_signals``).
Every decision is a line and an ``events.jsonl`` record (``events.py``); exit codes: ``options.py``; one supervisor
per log directory: ``ftrain.log_dir_lock``. Torch-free: config, heartbeat, the storage lease and the standard library.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import signal
import sys
import threading
import time
from pathlib import Path

from ftrain import procfs
from ftrain.ckpt import cas
from ftrain.ckpt.lease import Lease
from ftrain.ckpt.schedule import STORAGE_WAIT_ENV
from ftrain.config import Config, for_elastic, make_local_directories, storage_key
from ftrain.errors import (
    EXIT_STORAGE_HELD,
    STOPPED,
    Deliveries,
    UserError,
    raise_lost_stop,
    stop_code,
    stop_signals,
)
from ftrain.heartbeat import Heartbeat, read_heartbeats, write_stop_reason
from ftrain.log_dir_lock import claim_log_dir
from ftrain.redact import hide_credentials, redact_command
from ftrain.supervise.attempt import Attempt, Launcher, attempt_env, kill, new_log_dir, signal_name
from ftrain.supervise.events import EventLog
from ftrain.supervise.hang import ABSENT_AFTER, HANG_FLOOR, QUIET_PHASES, HangWatch
from ftrain.supervise.ledger import Ledger
from ftrain.supervise.link import connect, makes_plan, node_lease, rendezvous, worker_env
from ftrain.supervise.options import (
    EXIT_DONE,
    EXIT_PEER_LOST,
    Backend,
    Nodes,
    SupervisorOptions,
    parse_hang_timeout,
    parse_nodes,
    parse_workers,
)
from ftrain.supervise.outage import NEWEST_WITHIN, StorageWait, start_of
from ftrain.supervise.outcome import (
    Event,
    Outcome,
    classify,
    finished,
    not_admitted,
    peer_ended,
    stopped_by,
)
from ftrain.supervise.plan import Plan, plan_key
from ftrain.supervise.restarts import RestartPolicy
from ftrain.terminal import leave_the_terminal

POLL = 0.1
"""Seconds between two looks at torchrun and the heartbeats."""
PEER_POLL = 0.5
"""Seconds between two questions to node 0 while an attempt runs."""
LINGER = 30.0
"""Seconds node 0 keeps answering after the end, until every node has learnt the outcome."""


def supervise(options: SupervisorOptions, config: Config, train_args: list[str]) -> int:
    """Run training under supervision until it finishes or gives up; returns the exit code (see module doc).

    ``config``: the run's validated config; ``train_args``: the arguments of ``ftrain train`` it was read from
    (config file, ``--storage``, overrides), which every worker gets."""
    hang_timeout = parse_hang_timeout(options.hang_timeout)
    parse_workers(options.workers)  # before the storage is looked at (``with_nproc``), which makes its directory
    nodes = parse_nodes(options)
    options, chosen = with_nproc(options, nodes, config)
    for_elastic(config, nodes.least, nodes.count, options.nproc_per_node)  # before anything starts
    try:
        supervisor = Supervisor(options, nodes, hang_timeout, train_args, config)
    except ConnectionError as error:  # etcd-v2: etcd did not answer within --rdzv-timeout
        print(f"ftrain supervise: error: {error}", file=sys.stderr)
        return EXIT_PEER_LOST
    if chosen:
        supervisor.events("world", chosen)
    raise_lost_stop()  # before the supervisor takes the signals over
    for sig in stop_signals():  # to the end of the process: a signal once the run has ended (SLURM's
        signal.signal(sig, supervisor.on_signal)  # time limit as the job finishes) changes nothing, its exit code stays
    cas.stop_waiting_when(supervisor.waiting_stopped)
    log = lambda line: supervisor.events("lease", line, detail=line)  # noqa: E731
    refused = lambda line: print(f"ftrain supervise: error: {line}", file=sys.stderr)  # noqa: E731

    def claimed(held: Lease) -> int:  # with the storage's lease, the log directory too (claim.py)
        supervisor.storage_wait.reached = True
        with claim_log_dir(Path(config.log_dir), supervisor.events.node, "supervisor", storage_key(config.storage.url)):
            return supervisor.run(held)

    try:  # the lease is taken before anything is launched: an unreachable storage is waited out then too
        held = lambda: node_lease(config, nodes, options, log).run(claimed, refused, makes_plan(nodes, options))  # noqa: E731
        return supervisor.storage_wait.retrying(held, supervisor.end)
    except _Stop as stop:  # a signal or another node ended the run, in the loop or while the storage was waited for
        return supervisor.end(stop.ending)
    except cas.LockWaitStopped:  # a signal while it waited for the storage's lock, before it held the storage
        return supervisor.end(supervisor.stopped_without_workers())
    finally:
        supervisor.close()


def with_nproc(options: SupervisorOptions, nodes: Nodes, config: Config) -> tuple[SupervisorOptions, str]:
    """``options`` with ``--nproc-per-node`` where the command line left it out: on one node, the world size of the
    step the run resumes from, so that the command that started it, less that flag, trains on as before instead of
    resizing; else 1. And the line that says why, where it is not 1 or where the storage did not tell."""
    if options.nproc_per_node is not None:
        return options, ""
    world, why = 1, ""
    if nodes.count == 1:
        world, why = _trained_world(config)
    return dataclasses.replace(options, nproc_per_node=world), why


def _trained_world(config: Config) -> tuple[int, str]:
    choose = "--nproc-per-node N to choose"
    answered, start = start_of(config)
    if not answered:
        return 1, f"the storage did not say within {NEWEST_WITHIN:g} s how many ranks its run has: 1 worker ({choose})"
    if start is None:
        return 1, ""
    step, manifest = start
    world, cpus = int(manifest.get("world_size", 1)), os.cpu_count() or 1
    if world > cpus:
        return 1, f"step {step} was trained at {world} ranks, more than this node's {cpus} CPUs: 1 worker ({choose})"
    return world, f"{world} workers, as step {step} was trained (--nproc-per-node N to resize)" if world > 1 else ""


class _Stop(Exception):  # the run ends, wherever the supervisor was: ``supervise`` records it
    def __init__(self, ending: Outcome) -> None:
        super().__init__(ending.message)
        self.ending = ending


class Supervisor:
    def __init__(
        self,
        options: SupervisorOptions,
        nodes: Nodes,
        hang_timeout: float | None,
        train_args: list[str],
        config: Config,
    ) -> None:
        self.options = options
        self.nodes = nodes
        self.train_args = train_args
        log_dir = Path(config.log_dir)
        self.events = EventLog(log_dir / "events.jsonl", None)
        self.link = connect(nodes, options, self.events)
        self.node = self.link.node
        try:
            make_local_directories(config)  # once this node's options passed too, before its logs go there
        except UserError:
            self.link.close()
            raise
        self.events.node = self.node if nodes.count > 1 else None
        node_dir = f"node-{self.node}" if nodes.count > 1 else ""
        self.heartbeat_dir = (log_dir / "heartbeat" / node_dir).resolve()
        self.attempt_logs = log_dir / "torchrun" / node_dir
        self.hangs = HangWatch(hang_timeout, options.startup_grace, options.nproc_per_node)
        self.signals: list[int] = []
        self.deliveries = Deliveries()  # one stop delivered twice (``timeout``) is no second stop, which kills at once
        self.policy = RestartPolicy(options)
        self.ledger = Ledger(options.nproc_per_node, self.events)
        self.storage_wait = StorageWait(config.storage, options.storage_wait, self.events, self._sleep, log_dir=log_dir)
        self.last_step = config.iterations
        self.launcher = Launcher(options, log_dir / f"warm-pool{'-' + node_dir if node_dir else ''}.log")
        self.lease: Lease | None = None  # the storage's, held for the run (``run``)

    def on_signal(self, number: int, frame: object) -> None:
        if number == signal.SIGHUP:
            leave_the_terminal()
        if self.deliveries.new(number):
            self.signals.append(number)

    def waiting_stopped(self) -> bool:
        """Whether the main thread should stop waiting for the storage's lock: a signal came before the run held the
        storage (``cas.stop_waiting_when``), so nothing is written yet and nothing is to be saved."""
        return bool(self.signals) and self.lease is None and threading.current_thread() is threading.main_thread()

    def close(self) -> None:
        self.link.close()
        self.launcher.close()

    def run(self, lease: Lease) -> int:
        """Attempts, under the storage's ``lease`` (stopped once ``lost``), until the run ends (raises ``_Stop``)."""
        self.lease = lease
        try:
            self.link.begin(lease)
        except ConnectionError as error:  # etcd-v2: etcd did not answer within --rdzv-timeout
            raise _Stop(Outcome(Event.PEER_LOST, EXIT_PEER_LOST, str(error))) from None
        if self.nodes.count > 1 and self.storage_wait.holds(self.last_step):
            # a node that finds the run finished leaves (``_next_plan``), and torchrun cannot start without it
            raise _Stop(
                finished(self.last_step, f"nothing to train: pass iterations=N with N > {self.last_step} to train on")
            )
        plan = self._next_plan(None)
        waited = False  # the last attempt ended on an unusable storage
        while True:
            attempt = self._launch(plan)
            outcome = self._watch(attempt)
            if outcome.event == Event.REGROUP:
                plan = self._next_plan(plan)
                continue
            if not outcome.failed:
                raise _Stop(outcome)
            if outcome.event == Event.STORAGE_DOWN:
                ending = self.storage_wait(outcome.message, again=waited and not attempt.progressed)
                if ending is not None:
                    raise _Stop(ending)
                waited = True
                plan = self._next_plan(plan)
                self.events("restart", f"attempt {plan.attempt}: the storage is usable again", attempt=plan.attempt)
                continue
            waited = False
            delay = self.policy.judge(attempt)
            if isinstance(delay, Outcome):
                raise _Stop(delay)
            self._sleep(delay)
            plan = self._next_plan(plan)
            restarts = self.policy.restarts
            message = f"restart {restarts} (attempt {plan.attempt}) after {delay:.1f} s back-off"
            self.events("restart", message, attempt=plan.attempt, restarts=restarts, backoff=round(delay, 2))

    def _sleep(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            self._raise_if_signalled()
            time.sleep(min(POLL, max(0.0, deadline - time.monotonic())))
        self._raise_if_signalled()

    def _raise_if_signalled(self) -> None:
        if self.signals:
            raise _Stop(self.stopped_without_workers())

    def stopped_without_workers(self) -> Outcome:
        """The run's ending after a stop signal that came while no workers ran (recorded as a ``preempt``)."""
        self.events("preempt", signal=signal_name(self.signals[0]))
        code = stop_code(self.signals[0])
        newest = self.storage_wait.newest(self.policy.best_committed)  # as every other stop says it
        return stopped_by(code, "stopped by a signal while no workers ran", newest)

    def _next_plan(self, previous: Plan | None) -> Plan:
        """The next attempt to run (on several nodes: once node 0 has moved on from ``previous``, or ended the run)."""
        deadline = time.monotonic() + self.options.rdzv_timeout
        waiting = False
        while True:
            self._raise_if_signalled()
            try:
                plan = self.link.ask("plan")
            except OSError as error:
                plan = None
                if (not waiting or time.monotonic() > deadline) and self.storage_wait.holds(self.last_step):
                    raise _Stop(finished(self.last_step, "ended while this node was away")) from None
                if not waiting:
                    waiting = True
                    message = f"waiting up to {self.options.rdzv_timeout:g} s for {self.link.peer} ({error})"
                    print(f"ftrain supervise: {message}", file=sys.stderr, flush=True)
            if plan is not None and plan.final is not None:
                raise _Stop(peer_ended(plan.final))
            if plan is not None and (previous is None or plan_key(plan) != plan_key(previous)):
                return plan
            if time.monotonic() > deadline:
                raise _Stop(Outcome(Event.PEER_LOST, EXIT_PEER_LOST, f"{self.link.peer} did not answer"))
            time.sleep(PEER_POLL / 5)

    def _launch(self, plan: Plan) -> Attempt:
        token = plan.token(os.getpid())
        train_args, hidden = hide_credentials(self.train_args)
        env = attempt_env(self.heartbeat_dir, token, self.options.stop_grace, self.node, hidden)
        env |= {STORAGE_WAIT_ENV: str(self.storage_wait.limit), **worker_env(plan, self.nodes, self.lease.run_id)}
        logs = new_log_dir(self.attempt_logs, plan)
        arguments = rendezvous(plan, self.nodes, self.options)
        command, warm = self.launcher.command(arguments, train_args, logs)
        logged = redact_command(command)
        message = f"attempt {plan.attempt}: launching torchrun"
        self.events("start", message, attempt=plan.attempt, command=logged, logs=str(logs))
        self.hangs.restart(time.monotonic())
        undead = lambda line: self.events("undead", line, attempt=plan.attempt)  # noqa: E731
        return Attempt(plan, command, env | warm, token, logs, undead, lambda: bool(self.signals))

    def _watch(self, attempt: Attempt) -> Outcome:
        preempt_deadline = None
        now = time.monotonic()
        next_peer_check = now + PEER_POLL
        while True:
            time.sleep(POLL)
            previous, now = now, time.monotonic()
            if now - previous >= ABSENT_AFTER:
                self._absent(attempt, now - previous)
                if preempt_deadline is not None:  # the workers' grace to save did not run out while nobody ran
                    preempt_deadline += now - previous
            beats = read_heartbeats(self.heartbeat_dir)
            if self.ledger.observe(attempt, beats, now):
                self.hangs.restart(now)  # torchrun restarted the workers in a larger world: start-up again
            code = attempt.proc.poll()
            if code is not None:
                return self._exited(attempt, code)
            pid, seconds = self._torchrun_stopped(attempt, beats, now)
            if seconds > HANG_FLOOR:
                number = attempt.plan.attempt
                message = f"attempt {number}: torchrun (pid {pid}) stopped for {seconds:.1f} s after its workers ended"
                self.events("hang", f"{message}; killing it", attempt=number, torchrun=pid, seconds=seconds)
                attempt.kill()
                return self._exited(attempt, attempt.proc.returncode)
            if (lost := self.lease.lost) is not None:  # nothing they train from now on could be committed: stop them
                attempt.kill()
                self._log_exit(attempt, "stopped: another generation holds the storage")
                return Outcome(Event.STORAGE_HELD, EXIT_STORAGE_HELD, f"{lost}; its workers are stopped")
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
                self._failed(attempt, now - hang.seconds)  # down since the group went silent, not since it was seen
                attempt.kill()
                self._log_exit(attempt, hang.cause())
                return Outcome(Event.FAILED, None, "hang")
            if self.nodes.count > 1 and now >= next_peer_check:
                next_peer_check = now + PEER_POLL
                outcome = self._check_peers(attempt, now)
                if outcome is not None:
                    return outcome

    @staticmethod
    def _torchrun_stopped(attempt: Attempt, beats: dict[int, Heartbeat], now: float) -> tuple[int | None, float]:
        """A torchrun process stopped (SIGSTOP, a debugger) after its workers ended, and for how long (0.0 while there
        is none): it would never exit, and no heartbeat says so. Looked for once every worker's heartbeat says it
        has ended; stopped while they train, torchrun is left alone: they finish, or a hang among them ends the
        attempt."""
        ended = bool(beats) and all(beat.phase in QUIET_PHASES for beat in beats.values())
        pid = attempt.stopped_torchrun() if ended else None
        if pid is None:
            attempt.torchrun_stopped = None
            return None, 0.0
        attempt.torchrun_stopped = now if attempt.torchrun_stopped is None else attempt.torchrun_stopped
        return pid, round(now - attempt.torchrun_stopped, 1)

    def _absent(self, attempt: Attempt, seconds: float) -> None:
        """This supervisor did not run for ``seconds`` (stopped with its workers, a paused VM): it did not watch, so the
        workers' silence in that time is no hang."""
        self.hangs.credit(seconds)
        message = f"not running for {seconds:.1f} s (stopped or suspended): the workers' silence in it is not counted"
        self.events("absent", message, attempt=attempt.plan.attempt, seconds=round(seconds, 1))

    def _check_workers(self, attempt: Attempt, beats: dict[int, Heartbeat]) -> None:
        """A worker that died mid-training dooms the others (no collective can complete): SIGKILL them now rather
        than wait for them to fail on the broken group and for torchrun to notice (1-2 s measured here); torchrun
        still reports every exit code (the dead rank's own: a warm worker's stand-in is left to report it)."""
        dead = [r for r, b in beats.items() if b.phase not in QUIET_PHASES and procfs.state(b.pid) in ("gone", "Z")]
        if dead:
            latest = read_heartbeats(self.heartbeat_dir)  # a rank may have finished since we looked
            dead = [rank for rank in dead if latest.get(rank, beats[rank]).phase not in QUIET_PHASES]
        if not dead:
            return
        attempt.dead = sorted(dead)
        attempt.killed = set(beats) - set(dead)
        self.events("worker_died", attempt=attempt.plan.attempt, ranks=attempt.dead)
        for rank in attempt.killed:
            kill(beats[rank].pid, signal.SIGKILL)

    def _check_peers(self, attempt: Attempt, now: float) -> Outcome | None:
        """Several nodes: stop this node's group when another node failed the attempt or ended the run."""
        plan = self._tell("plan")
        if plan is None or plan.final == EXIT_DONE or plan.final in STOPPED:
            return None
        if plan.final is not None:
            attempt.stop(self.options.stop_grace)
            self._log_exit(attempt, "stopped: another node ended the run")
            return peer_ended(plan.final)
        if plan_key(plan) == plan_key(attempt.plan):
            return None
        if plan.left is not None:
            attempt.stop(self.options.stop_grace)  # the workers save, as they do for the leaving node's stop
            return self._regroup(attempt, plan, f"stopped: node {plan.left} left")
        message = f"attempt {attempt.plan.attempt}: another node failed; stopping this node's workers"
        self.events("superseded", message, attempt=attempt.plan.attempt)
        self._failed(attempt, now)
        attempt.stop(self.options.stop_grace)
        self._log_exit(attempt, "stopped: another node failed")
        return Outcome(Event.FAILED, None, "superseded")

    def _preempt(self, attempt: Attempt) -> None:
        name = signal_name(self.signals[0])
        leaves = "; this node leaves, the others go on from the save" if self._leaves_alone() else ""
        asking = f"{name}: asking the workers to save and exit (SIGKILL in {self.options.stop_grace:g} s){leaves}"
        self.events("preempt", asking, attempt=attempt.plan.attempt, signal=name)
        if self._leaves_alone():
            self._tell("leave", node=self.node, **plan_key(attempt.plan))
        elif self.nodes.count > 1:
            self._tell("finish", code=stop_code(self.signals[0]))
        write_stop_reason(self.heartbeat_dir, self.signals[0])
        attempt.terminate(signal.SIGHUP if self.signals[0] == signal.SIGHUP else signal.SIGTERM)

    def _exited(self, attempt: Attempt, code: int) -> Outcome:
        now = time.monotonic()
        orphans = attempt.workers()
        if orphans and not self.signals:
            # torchrun died, its workers train on: tell the other nodes first (their workers' coming save-and-exit
            # reads as a restart there, not as a preemption), then let the orphans save
            self._failed(attempt, now)
        if orphans:
            attempt.stop(self.options.stop_grace)  # ends with kill() too
        else:
            attempt.kill()
        phases = self._phases(attempt)
        cause = attempt.cause(code) if code or orphans else "exit code 0"
        current = self._tell("plan") if code in STOPPED and self.nodes.count > 1 else None  # None: not known
        moved = current is not None and plan_key(current) != plan_key(attempt.plan)
        superseded = moved or (self.nodes.elastic and current is not None and current.final is None)  # see classify
        stopped = stop_code(self.signals[0]) if self.signals else None
        committed = attempt.committed if attempt.committed is not None else self.policy.best_committed
        outcome = classify(code, cause, attempt.culprit(), stopped, bool(orphans), phases, superseded, committed)
        if not outcome.failed and not self._ends_alone(outcome):  # the run ends: the step a rerun resumes from, as
            committed = self.storage_wait.newest(committed)  # the storage has it (others going on commit newer ones)
            self.ledger.seen_commit(committed)
            outcome = classify(code, cause, attempt.culprit(), stopped, bool(orphans), phases, superseded, committed)
        if outcome.event == Event.FAILED and (full := self.storage_wait.disk_full()) is not None:
            outcome = Outcome(Event.STORAGE_DOWN, None, full)  # restarts would fail alike: wait for space instead
        if outcome.event == Event.TOO_FEW_NODES and self._keeps_no_plan():
            outcome = not_admitted(committed)
        if moved and current.left is not None and outcome.failed:  # saved for a node that left: no failure
            return self._regroup(attempt, current, cause, phases)
        self._log_exit(attempt, cause, f"attempt {attempt.plan.attempt}: {cause}" if outcome.failed else "", phases)
        if outcome.failed:
            self._failed(attempt, now)
        return outcome

    def _regroup(self, attempt: Attempt, plan: Plan, cause: str, phases: set[str] | None = None) -> Outcome:
        """Another node left (preempted) and the workers saved: the others go on without it, no failure counted."""
        self._log_exit(attempt, cause, phases=phases)
        message = f"attempt {attempt.plan.attempt}: node {plan.left} left the run; regrouping without it"
        self.ledger.left.add(plan.left)
        self.events("regroup", message, attempt=attempt.plan.attempt, left=plan.left)
        return Outcome(Event.REGROUP, None, message)

    def _phases(self, attempt: Attempt) -> set[str]:
        """The phases of the final heartbeats (after the attempt's processes are gone)."""
        beats = read_heartbeats(self.heartbeat_dir)
        self.ledger.observe(attempt, beats, time.monotonic())
        return {beat.phase for beat in beats.values()}

    def _log_exit(self, attempt: Attempt, cause: str, message: str = "", phases: set[str] | None = None) -> None:
        """The ``exit`` event; ``phases``: the final heartbeat phases, if the caller has read them already."""
        self.events("exit", message, **attempt.exit_fields(cause, self._phases(attempt) if phases is None else phases))

    def _failed(self, attempt: Attempt, now: float) -> None:
        """Once per attempt: remember the failure for the summary and tell node 0 (one node: the local counter)."""
        if attempt.reported:
            return
        attempt.reported = True
        self.ledger.failed(attempt.completed, now)
        self._tell("fail", **plan_key(attempt.plan))

    def _tell(self, op: str, **fields) -> Plan | None:
        """Ask the plan's keeper (node 0 or etcd); its plan, or None when it cannot be reached."""
        with contextlib.suppress(OSError):
            return self.link.ask(op, **fields)
        return None

    def end(self, ending: Outcome) -> int:
        """The run ends: record it, tell the other nodes, sum up; the exit code."""
        self.events(ending.event, ending.message, code=ending.code)
        if self.nodes.count > 1 and not self._ends_alone(ending):
            self._tell("finish", code=ending.code)
            self.link.settle(self.nodes.count, LINGER)
        self.ledger.summarize(ending.event, ending.code, self.policy.restarts, time.monotonic())
        return ending.code

    def _ends_alone(self, ending: Outcome) -> bool:
        """Whether ``ending`` ends this node only: its preemption when it ``_leaves_alone``, or its rendezvous timeout
        when ``not_admitted`` (a node that came back late and was not taken in must not stop those that train)."""
        return self._leaves_alone() if ending.event == Event.PREEMPTED else ending.event == Event.NOT_ADMITTED

    def _keeps_no_plan(self) -> bool:
        """An elastic node that neither keeps the plan nor hosts the rendezvous: on etcd-v2 any, on c10d not node 0."""
        return self.nodes.elastic and (self.nodes.backend is Backend.ETCD or self.node != 0)

    def _leaves_alone(self) -> bool:
        """Whether this node's preemption leaves the others training from the workers' save: an elastic run with MIN
        nodes left without it, on etcd-v2 or (c10d) not node 0, which keeps the plan and hosts the rendezvous."""
        return self._keeps_no_plan() and len(self.ledger.nodes) - 1 >= self.nodes.least
