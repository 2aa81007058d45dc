"""Recovery benchmark of ``ftrain supervise``: real faults injected into a supervised 2-rank run of configs/smoke.yaml.

    .venv/bin/python launch/bench_recovery.py [--trials 10] [--scenarios kill-rank0-iteration hang ...]

Scenarios: SIGKILL of rank 0 or 1 in the middle of an iteration or of a save (a step directory without its manifest
yet, or the ``checkpoint`` phase), SIGSTOP of rank 1 (a hang, ``--hang-timeout 3``), SIGTERM to the supervisor
(preemption) and the same command again, and SIGKILL of node 1's worker of two supervisors as two nodes. Recovery
is from the fault to the next completed iteration (the ``recovered`` event; for preemption, the rerun's first
iteration); lost iterations: completed before the fault, not in the step resumed from. Kills and hangs: every trial
into one long run.

``node-loss``: three elastic nodes (``--nnodes 2:3``, one rank each, ``--rejoin-timeout 5``); node 2's supervisor,
torchrun and worker are SIGKILLed at once, then started again. ``etcd-node-loss`` and ``etcd-preempt``: the same
three nodes meeting through a private etcd (``--rdzv-backend etcd-v2``: no node is special), each trial hitting the
node whose worker is rank 0 (its whole process tree SIGKILLed, or SIGTERM to its supervisor: it saves and leaves
with 143), then starting it again (a new node to etcd). Two rows each (the ``resize`` events): from the fault to the
first iteration of the 2-rank world, and from the node's start to the first of the 3-rank world.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import secrets
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from ftrain import procfs  # noqa: E402
from ftrain.ckpt.format import CHECKPOINTS, MANIFEST  # noqa: E402
from ftrain.errors import EXIT_PREEMPTED  # noqa: E402
from ftrain.heartbeat import read_heartbeats  # noqa: E402
from ftrain.supervise.auth import SECRET_ENV  # noqa: E402
from ftrain.supervise.coordinator import free_port  # noqa: E402

from etcd_server import etcd_server  # noqa: E402 - beside this script

OVERRIDES = ["iterations=1000000", "dist_timeout=10", "log.console=false"]
HANG_TIMEOUT = 3
SCENARIOS = (
    "kill-rank0-iteration",
    "kill-rank1-iteration",
    "kill-rank0-save",
    "kill-rank1-save",
    "hang",
    "preempt",
    "two-nodes-kill",
    "node-loss",
    "etcd-node-loss",
    "etcd-preempt",
)
REJOIN_TIMEOUT = 5


class Supervised:
    """One ``ftrain supervise`` process on ``storage``; its log directory is ``log_dir`` (default: ``storage``, a
    local directory), its console output ``<log_dir>.log``."""

    def __init__(
        self,
        storage: Path | str,
        *options: str,
        node: int | None = None,
        env: dict | None = None,
        config: str = "configs/smoke.yaml",
        overrides: list[str] = OVERRIDES,
        log_dir: Path | None = None,
        hang_timeout: str = str(HANG_TIMEOUT),
    ) -> None:
        self.storage = storage
        self.log_dir = Path(storage) if log_dir is None else log_dir
        self.node = node
        self.heartbeats = self.log_dir / "heartbeat" / (f"node-{node}" if node is not None else "")
        command = [sys.executable, "-m", "ftrain", "supervise", "--hang-timeout", hang_timeout, *options]
        command += [config, "--storage", str(storage), *overrides]
        if log_dir is not None:
            command.append(f"log_dir={log_dir}")
        self._read = 0
        self._events: list[dict] = []
        self.earlier_resumes = len(self.events("resumed"))  # of earlier runs on the same storage
        log = open(f"{self.log_dir}.log", "ab")  # noqa: SIM115 - the child writes to it for its whole life
        self.proc = subprocess.Popen(
            command, cwd=REPO, env={**os.environ, **(env or {})}, stdout=log, stderr=subprocess.STDOUT
        )

    def events(self, name: str) -> list[dict]:
        """This node's ``name`` events so far (read incrementally: polling must not steal the workers' CPU)."""
        path = self.log_dir / "events.jsonl"
        if path.exists():
            with path.open("rb") as file:
                file.seek(self._read)
                data = file.read()
            complete = data[: data.rfind(b"\n") + 1]
            self._read += len(complete)
            self._events += [json.loads(line) for line in complete.splitlines()]
        return [e for e in self._events if e["event"] == name and (self.node is None or e.get("node") == self.node)]

    def next_event(self, name: str, seen: int, timeout: float = 180) -> dict:
        """The first ``name`` event after the ``seen`` ones."""
        return wait_for(lambda: self.events(name)[seen:], timeout, f"a {name} event", interval=0.02)[0]

    def training(self, past: int, ranks: int = 2, timeout: float = 120) -> dict:
        """Heartbeats once every rank trains beyond iteration ``past``."""

        def ready():
            beats = read_heartbeats(self.heartbeats)
            busy = [b for b in beats.values() if b.iteration > past and b.phase in ("rollout", "update")]
            return beats if len(busy) == ranks else None

        return wait_for(ready, timeout, f"training past iteration {past}")

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(timeout=120)


def wait_for(predicate, timeout: float, what: str, interval: float = 0.005):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if value := predicate():
            return value
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


def save_in_flight(storage: Path, beats_dir: Path) -> bool:
    """A checkpoint is being written: a step directory without its manifest, or a rank in the checkpoint phase."""
    steps = os.scandir(storage / CHECKPOINTS) if (storage / CHECKPOINTS).exists() else []
    unfinished = any(not os.path.exists(os.path.join(step.path, MANIFEST)) for step in steps)
    return unfinished or any(beat.phase == "checkpoint" for beat in read_heartbeats(beats_dir).values())


def resumed_step(run: Supervised) -> int:
    """The step this supervisor's first attempt resumed from (0: fresh)."""
    return run.next_event("resumed", run.earlier_resumes)["step"] or 0


def fault_trials(scenario: str, trials: int, work: Path) -> list[dict]:
    """Every trial into one long supervised run: inject, wait for the ``recovered`` event, repeat."""
    storage = work / scenario / "run"
    storage.parent.mkdir(parents=True)
    run = Supervised(storage, "--nproc-per-node", "2", "--max-restarts", str(trials + 5))
    results = []
    try:
        for _ in range(trials):
            recovered = len(run.events("recovered"))
            restarts = len(run.events("restart"))
            base = resumed_step(run) if not results else results[-1]["step"]
            beats = run.training(base + 2)
            rank = 0 if "rank0" in scenario else 1
            if scenario.endswith("-save"):
                wait_for(lambda: save_in_flight(storage, run.heartbeats), 60, "a save in flight", interval=0.0005)
                beats = read_heartbeats(run.heartbeats)
            at = time.time()
            os.kill(beats[rank].pid, signal.SIGSTOP if scenario == "hang" else signal.SIGKILL)
            event = run.next_event("recovered", recovered)
            results.append(
                {
                    "seconds": event["time"] - at,
                    "lost": event["lost"],
                    "restarts": len(run.events("restart")) - restarts,
                    "step": event["step"],
                }
            )
            print(f"  {scenario} trial {len(results)}: {format_trial(results[-1])}", flush=True)
    finally:
        run.stop()
    return results


def preempt_trials(trials: int, work: Path) -> list[dict]:
    """SIGTERM to the supervisor, then the same command again; every trial continues the same storage."""
    storage = work / "preempt" / "run"
    storage.parent.mkdir(parents=True)
    results = []
    for _ in range(trials):
        run = Supervised(storage, "--nproc-per-node", "2")
        beats = run.training(resumed_step(run) + 2)
        completed = max(beat.iteration for beat in beats.values())
        at = time.time()
        run.proc.send_signal(signal.SIGTERM)
        assert run.proc.wait(timeout=120) == EXIT_PREEMPTED
        rerun = Supervised(storage, "--nproc-per-node", "2")
        step = resumed_step(rerun)
        rerun.training(step)
        lost = max(0, completed - step)
        results.append({"seconds": time.time() - at, "lost": lost, "restarts": 1, "step": step})
        print(f"  preempt trial {len(results)}: {format_trial(results[-1])}", flush=True)
        rerun.stop()
    return results


def two_node_trials(trials: int, work: Path) -> list[dict]:
    """Two supervisors as two nodes on 127.0.0.1 (one rank each); SIGKILL node 1's worker, both must recover."""
    storage = work / "two-nodes" / "run"
    storage.parent.mkdir(parents=True)
    endpoint = f"127.0.0.1:{free_port()}"
    secret = {SECRET_ENV: secrets.token_hex(32)}
    nodes = [
        Supervised(
            storage,
            *("--nproc-per-node", "1", "--nnodes", "2", "--node-rank", str(node), "--rdzv-endpoint", endpoint),
            *("--max-restarts", str(trials + 5)),
            node=node,
            env=secret,
        )
        for node in (0, 1)
    ]
    results = []
    try:
        for _ in range(trials):
            recovered = [len(node.events("recovered")) for node in nodes]
            restarts = [len(node.events("restart")) for node in nodes]
            base = resumed_step(nodes[1]) if not results else results[-1]["step"]
            beats = nodes[1].training(base + 2, ranks=1)
            at = time.time()
            os.kill(beats[1].pid, signal.SIGKILL)
            events = [node.next_event("recovered", count) for node, count in zip(nodes, recovered, strict=True)]
            results.append(
                {
                    "seconds": max(event["time"] for event in events) - at,
                    "lost": max(event["lost"] for event in events),
                    "restarts": max(len(n.events("restart")) - r for n, r in zip(nodes, restarts, strict=True)),
                    "step": events[0]["step"],
                }
            )
            print(f"  two-nodes-kill trial {len(results)}: {format_trial(results[-1])}", flush=True)
    finally:
        for node in nodes:
            node.stop()
    return results


def node_loss_trials(trials: int, work: Path) -> dict[str, list[dict]]:
    """Three elastic nodes on 127.0.0.1; each trial loses node 2 for good, then starts it again."""
    storage = work / "node-loss" / "run"
    storage.parent.mkdir(parents=True)
    endpoint = f"127.0.0.1:{free_port()}"
    secret = {SECRET_ENV: secrets.token_hex(32)}
    options = ("--nproc-per-node", "1", "--nnodes", "2:3", "--rdzv-endpoint", endpoint)
    options += ("--rejoin-timeout", str(REJOIN_TIMEOUT), "--max-restarts", str(trials + 5))

    def node(rank: int) -> Supervised:
        return Supervised(storage, *options, "--node-rank", str(rank), node=rank, env=secret)

    nodes = [node(rank) for rank in range(3)]
    results: dict[str, list[dict]] = {"node-loss-shrink": [], "node-return-grow": []}
    try:
        nodes[0].training(resumed_step(nodes[0]) + 2, ranks=1)
        for _ in range(trials):
            lose_and_return(nodes, 2, kill_tree, lambda: node(2), nodes[0], results, "node-loss")
    finally:
        for each in nodes:
            each.stop()
    return results


def etcd_trials(fault: str, trials: int, work: Path) -> dict[str, list[dict]]:
    """Three elastic nodes meeting through etcd; each trial hits rank 0's node (``fault``: ``kill`` its process tree,
    or ``preempt``: SIGTERM to its supervisor), then starts it again."""
    storage = work / f"etcd-{fault}" / "run"
    storage.parent.mkdir(parents=True)
    results: dict[str, list[dict]] = {f"etcd-rank0-node-{fault}": [], f"etcd-node-return-{fault}": []}
    with etcd_server(storage.parent) as endpoint:
        options = ("--nproc-per-node", "1", "--nnodes", "2:3", "--rdzv-backend", "etcd-v2", "--rdzv-endpoint", endpoint)
        options += ("--rdzv-id", "bench", "--rejoin-timeout", str(REJOIN_TIMEOUT), "--max-restarts", str(trials + 5))
        nodes = [Supervised(storage, *options) for _ in range(3)]
        lose = kill_tree if fault == "kill" else preempt
        try:
            for _ in range(trials):
                rank0, observer = numbered(storage, nodes)
                start = lambda: Supervised(storage, *options)  # noqa: E731 - a new node to etcd
                lose_and_return(nodes, nodes.index(rank0), lose, start, observer, results, f"etcd-{fault}")
        finally:
            for each in nodes:
                each.stop()
    return results


def lose_and_return(
    nodes: list[Supervised],
    index: int,
    lose: Callable[[subprocess.Popen], None],
    start: Callable[[], Supervised],
    observer: Supervised,
    results: dict[str, list[dict]],
    label: str,
) -> None:
    """One trial: ``lose`` node ``index`` through its supervisor's process (``kill_tree``: the machine is gone, or
    ``preempt``), wait for the ``observer``'s shrink, ``start`` the node again, wait for the grow; the two ``resize``
    events go to ``results``' two rows (shrink, then grow)."""
    shrinks, grows = results
    resizes = len(observer.events("resize"))
    at = time.time()
    lose(nodes[index].proc)
    shrink = observer.next_event("resize", resizes)
    results[shrinks].append(resize_result(shrink, at))
    observer.training((shrink["step"] or 0) + 2, ranks=1)  # None: resumed fresh
    at = time.time()
    nodes[index] = start()
    grow = observer.next_event("resize", resizes + 1)
    results[grows].append(resize_result(grow, at))
    observer.training((grow["step"] or 0) + 2, ranks=1)
    shrunk, grown = format_trial(results[shrinks][-1]), format_trial(results[grows][-1])
    print(f"  {label} trial {len(results[grows])}: shrink {shrunk}; grow {grown}", flush=True)


def preempt(supervisor: subprocess.Popen) -> None:
    """SIGTERM to a node's supervisor: the workers save, and it leaves with 143."""
    supervisor.send_signal(signal.SIGTERM)
    assert supervisor.wait(timeout=120) == EXIT_PREEMPTED


def numbered(storage: Path, nodes: list[Supervised]) -> tuple[Supervised, Supervised]:
    """Once a 3-rank world trains past its first commit (a fault before a supervisor saw the world of 3 counts as a
    restart, not a resize): every node learns its number (from etcd); the nodes of rank 0 and of rank 1 (to watch)."""

    def world_of_three() -> dict[int, tuple[Supervised, Path]] | None:
        found = {}
        for directory in storage.glob("heartbeat/node-*"):
            for beat in read_heartbeats(directory).values():
                owner = [node for node in nodes if beat.pid in procfs.descendants(node.proc.pid)]
                if beat.world == 3 and beat.committed_step and beat.phase in ("rollout", "update") and owner:
                    found[beat.rank] = (owner[0], directory)
        return found if len(found) == 3 else None

    found = wait_for(world_of_three, 180, "a world of 3 ranks training", interval=0.2)
    for owner, directory in found.values():
        owner.node, owner.heartbeats = int(directory.name.removeprefix("node-")), directory
    return found[0][0], found[1][0]


def kill_tree(proc: subprocess.Popen) -> None:
    """SIGKILL a process and everything below it at once, like a machine that lost power."""
    for pid in [proc.pid, *procfs.descendants(proc.pid)]:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    proc.wait()


def resize_result(event: dict, since: float) -> dict:
    return {"seconds": event["time"] - since, "lost": event["lost"], "restarts": 1, "step": event["step"]}


def format_trial(result: dict) -> str:
    return f"{result['seconds']:.2f} s, {result['lost']} iterations lost, {result['restarts']} restart(s)"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--scenarios", nargs="+", choices=SCENARIOS, default=list(SCENARIOS))
    parser.add_argument("--keep", action="store_true", help="keep the run directories (printed)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="ftrain-bench-recovery-"))
    summary = {}
    for scenario in args.scenarios:
        print(f"{scenario}:", flush=True)
        if scenario == "preempt":
            summary[scenario] = preempt_trials(args.trials, work)
        elif scenario == "two-nodes-kill":
            summary[scenario] = two_node_trials(args.trials, work)
        elif scenario == "node-loss":
            summary.update(node_loss_trials(args.trials, work))
        elif scenario.startswith("etcd-"):
            summary.update(etcd_trials("kill" if scenario == "etcd-node-loss" else "preempt", args.trials, work))
        else:
            summary[scenario] = fault_trials(scenario, args.trials, work)
    header = ("scenario", "trials", "median s", "worst s", "lost med", "lost max", "1st restart")
    print("\n{:<22} {:>6} {:>9} {:>8} {:>9} {:>9} {:>12}".format(*header))
    for scenario, results in summary.items():
        seconds = [r["seconds"] for r in results]
        lost = [r["lost"] for r in results]
        first = sum(r["restarts"] == 1 for r in results)
        print(
            f"{scenario:<22} {len(results):>6} {statistics.median(seconds):>9.2f} {max(seconds):>8.2f} "
            f"{statistics.median(lost):>9g} {max(lost):>9} {first:>6}/{len(results):<5}"
        )
    if args.keep:
        print(f"runs kept in {work}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
