"""Goodput benchmark of ``ftrain supervise``: the shipped HalfCheetah config at 2 ranks on S3, hit by a fault every
PERIOD seconds, against the same run uninterrupted.

    .venv/bin/python launch/bench_chaos.py [--iterations 2500] [--period 30] [--seed 0] [--outage 60]

Storage is a moto S3 server behind a TCP proxy (``launch/s3_outage.py``). First the run goes uninterrupted, then
again on a fresh bucket while faults come in a fixed rotation whose order, target ranks and time jitter are drawn
from ``--seed`` (two runs with the same seed inject the same sequence): a worker SIGKILLed, a worker SIGSTOPped (a
hang), the supervisor SIGTERMed and the same command run again, a flipped byte in the newest committed shard plus a
worker SIGKILLed, the whole process tree SIGKILLed and the same command run again, and the S3 port refusing for
``--outage`` seconds. A supervisor that exits otherwise (a failure the product does not survive yet) is reported
with its exit code and the fault it came after, and the same command is run again (``--max-reruns``). A chaos run
that takes over ``--max-slowdown`` times the uninterrupted one (faults faster than it recovers) is given up.

Printed: goodput = uninterrupted wall time / chaos wall time, the faults, iterations lost, whether the final
``state_sha256`` equals the uninterrupted run's, the lost time in the buckets of Google's ml-goodput-measurement
(program start-up, checkpoint restore, wasted progress, detection and infrastructure recovery, checkpoint save, and
the rest), and where each restart's time goes (launch to ready, restore, first iteration), next to the cost of
importing torch, mujoco, rsl_rl and gymnasium alone: what a restart of cold workers (``--workers cold``) adds, and
warm ones (forked from the pool that imported them) do not pay.

The timeline comes from the supervisor's ``events.jsonl`` (torchrun launches, resumed steps) and the heartbeats,
polled every ``POLL`` seconds (each heartbeat carries the time it was written): a worker's first ``start`` beat
(imports, process group, environments and model built), its second ``start`` beat (checkpoint restored), its first
beat past the step it resumed from (first iteration done), and the time it spent in the ``checkpoint`` phase.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import random
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import s3fs
from bench_recovery import Supervised, kill_tree
from chaos_timeline import Timeline, attempts, lost_iterations, stopped

from ftrain import procfs
from ftrain.ckpt.format import read_manifest, shard_name, step_dir
from ftrain.ckpt.steps import scan
from ftrain.ckpt.storage import Storage
from ftrain.errors import EXIT_PREEMPTED
from ftrain.heartbeat import Heartbeat

from s3_outage import S3Server  # beside this script

KINDS = ("worker-kill", "worker-hang", "preempt-rerun", "corrupt-kill", "tree-kill", "storage-outage")
NEEDS_TRAINING = {"worker-kill", "worker-hang", "preempt-rerun", "corrupt-kill", "tree-kill"}
"""Faults injected only while every rank trains (a process fault during a restart would hit nothing)."""
JITTER = 0.1
"""Each fault's time is drawn within +-JITTER periods of its slot."""
POLL = 0.02
KEY, SECRET, REGION = "bench-chaos-key", "bench-chaos-secret", "us-east-1"
IMPORTS = "import torch, mujoco, rsl_rl, gymnasium"
RUNNING = (["R"], ["S"], ["D"])
"""Process states of a live worker that is not stopped (``T``) or gone."""


@dataclass
class Fault:
    kind: str
    gap: float
    """Seconds after the previous fault (the first: after the chaos run's start)."""
    rank: int
    injected: float | None = None
    note: str = ""


def fault_plan(seed: int, period: float, count: int) -> list[Fault]:
    """The same faults for the same seed: the rotation's order, each fault's target rank and time jitter. Each
    fault comes a period after the previous one was injected (not on a fixed clock: a fault delayed by a recovery
    must not bring the next ones at once)."""
    rng = random.Random(seed)
    order = rng.sample(KINDS, len(KINDS))
    return [
        Fault(order[k % len(order)], period * (1 + rng.uniform(-JITTER, JITTER)), rng.randrange(2))
        for k in range(count)
    ]


class Bench:
    def __init__(self, args: argparse.Namespace, work: Path) -> None:
        self.args = args
        self.work = work
        self.server = S3Server(work / "moto.log")
        self.env = {
            "AWS_ENDPOINT_URL": self.server.endpoint_url,
            "AWS_ACCESS_KEY_ID": KEY,
            "AWS_SECRET_ACCESS_KEY": SECRET,
            "AWS_DEFAULT_REGION": REGION,
            "OMP_NUM_THREADS": "1",
        }

    def storage(self, name: str) -> tuple[str, Storage]:
        """A fresh bucket's run URL, and a Storage on it that bypasses the proxy (it works during an outage)."""
        url = f"s3://bench-chaos-{name}/run"
        options = {"endpoint_url": self.server.direct_url, "key": KEY, "secret": SECRET}
        s3fs.S3FileSystem(**options).mkdir(f"bench-chaos-{name}")
        return url, Storage.open(url, options)

    def supervise(self, url: str, log_dir: Path) -> Supervised:
        overrides = [f"iterations={self.args.iterations}", "log.console=false", *self.args.set]
        options = ("--nproc-per-node", "2", "--max-restarts", "1000")
        return Supervised(
            url,
            *options,
            env=self.env,
            config="configs/halfcheetah.yaml",
            overrides=overrides,
            log_dir=log_dir,
            hang_timeout="auto",
        )

    def straight(self) -> dict:
        url, storage = self.storage("straight")
        timeline = Timeline(self.work / "straight" / "heartbeat")
        started = time.time()
        run = self.supervise(url, self.work / "straight")
        while run.proc.poll() is None:
            timeline.poll()
            time.sleep(POLL)
        wall = time.time() - started
        if run.proc.returncode != 0:
            raise SystemExit(f"the uninterrupted run exited {run.proc.returncode}: see {self.work}/straight.log")
        return {"wall": wall, "digest": final_digest(storage), "timeline": timeline}

    def chaos(self, straight_wall: float) -> dict:
        """The chaos run; ``wall`` None if it did not finish (``--max-reruns`` unexpected exits, or slower than
        ``--max-slowdown`` times the uninterrupted run: faults that come faster than the run can recover)."""
        url, storage = self.storage("chaos")
        log_dir = self.work / "chaos"
        timeline = Timeline(log_dir / "heartbeat")
        plan = fault_plan(self.args.seed, self.args.period, count=10_000)
        state = ChaosState(url, storage, log_dir, plan)
        started = state.spawned[0]
        state.run = self.supervise(url, log_dir)
        try:
            while True:
                now = time.time()
                if state.outage_ends is not None and now >= state.outage_ends:
                    self.server.restore()
                    state.outage_ends = None
                beats = timeline.poll()
                code = state.run.proc.poll()
                if code is not None:
                    if code == 0:
                        break
                    if not self.ended(state, code):
                        return {"wall": None, "state": state, "timeline": timeline}
                    continue
                if now - started > self.args.max_slowdown * straight_wall:
                    print(f"  giving up: {now - started:.0f} s, over {self.args.max_slowdown:g}x the uninterrupted run")
                    return {"wall": None, "state": state, "timeline": timeline}
                fault = plan[len(state.injected)]
                previous = state.injected[-1].injected if state.injected else started
                if now - previous >= fault.gap and (fault.kind not in NEEDS_TRAINING or training(beats)):
                    self.inject(state, fault, beats)
                time.sleep(POLL)
            wall = time.time() - started
            return {"wall": wall, "digest": final_digest(storage), "state": state, "timeline": timeline}
        finally:
            self.server.restore()
            for pid in state.stopped:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGCONT)
            state.run.stop()

    def ended(self, state: ChaosState, code: int) -> bool:
        """The supervisor exited non-zero: run the same command again (after an outage we caused has ended). False
        once ``--max-reruns`` unexpected exits happened."""
        expected = state.expect_exit == code
        state.expect_exit = None
        at = len(state.injected)
        if not expected:
            exits = state.run.events("exit")
            cause = exits[-1]["cause"] if exits else "no attempt ended"
            state.endings.append((code, at, cause))
            print(f"  run ended with exit code {code} at fault {at} ({cause}); running the same command again")
            if len(state.endings) > self.args.max_reruns:
                print(f"  giving up after {len(state.endings)} unexpected exits")
                return False
            while state.outage_ends is not None and time.time() < state.outage_ends:
                time.sleep(POLL)
            if state.outage_ends is not None:
                self.server.restore()
                state.outage_ends = None
        state.reruns += 1
        state.spawned.append(time.time())
        state.run = self.supervise(state.url, state.log_dir)
        return True

    def inject(self, state: ChaosState, fault: Fault, beats: dict[int, Heartbeat]) -> None:
        fault.injected = time.time()
        state.injected.append(fault)
        pid = beats[fault.rank].pid if fault.rank in beats else None
        if fault.kind == "worker-kill":
            os.kill(pid, signal.SIGKILL)
        elif fault.kind == "worker-hang":
            os.kill(pid, signal.SIGSTOP)
            state.stopped.append(pid)
        elif fault.kind == "preempt-rerun":
            state.expect_exit = EXIT_PREEMPTED
            state.run.proc.send_signal(signal.SIGTERM)
        elif fault.kind == "corrupt-kill":
            fault.note = flip_newest_shard(state.storage, fault.rank)
            os.kill(pid, signal.SIGKILL)
        elif fault.kind == "tree-kill":
            kill_tree(state.run.proc)
            state.expect_exit = state.run.proc.returncode
        else:
            self.server.refuse()
            state.outage_ends = fault.injected + self.args.outage
        at = fault.injected - state.spawned[0]
        print(f"  fault {len(state.injected)} at {at:.1f} s: {fault.kind} (rank {fault.rank}) {fault.note}")


@dataclass
class ChaosState:
    url: str
    storage: Storage
    log_dir: Path
    plan: list[Fault]
    run: Supervised | None = None
    injected: list[Fault] = field(default_factory=list)
    stopped: list[int] = field(default_factory=list)
    spawned: list[float] = field(default_factory=lambda: [time.time()])
    """When each supervisor process was started (the first, then every rerun)."""
    expect_exit: int | None = None
    endings: list[tuple[int, int, str]] = field(default_factory=list)
    """Unexpected supervisor exits: (exit code, faults injected by then, the last attempt's cause)."""
    reruns: int = 0
    outage_ends: float | None = None


def training(beats: dict[int, Heartbeat]) -> bool:
    """Both ranks in rollout or update, their processes running (not stopped by an earlier fault)."""
    running = [
        b for b in beats.values() if b.phase in ("rollout", "update") and procfs.stat_fields(b.pid)[:1] in RUNNING
    ]
    return len(running) >= 2


def flip_newest_shard(storage: Storage, rank: int) -> str:
    """Invert one byte in the middle of ``rank``'s shard of the newest committed step (like bit rot), if an older
    verified step remains to resume from (a run whose only checkpoint is damaged rightly refuses to start over)."""
    steps = sorted(info.step for info in scan(storage) if info.status == "verified")
    if len(steps) < 2:
        return f"(not damaged: {len(steps)} verified step(s), none older to resume from)"
    path = f"{step_dir(steps[-1])}/{shard_name(rank)}"
    data = bytearray(storage.read(path))
    data[len(data) // 2] ^= 0xFF
    storage.write_replace(path, bytes(data))
    return f"(flipped a byte of step {steps[-1]}'s {shard_name(rank)})"


def final_digest(storage: Storage) -> tuple[int, str]:
    steps = [info.step for info in scan(storage) if info.status == "verified"]
    manifest = read_manifest(storage, max(steps))
    return max(steps), manifest["state_sha256"]


def import_seconds(repeats: int = 3) -> float:
    """Median wall time of a fresh interpreter importing the worker's heavy modules, nothing else."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", IMPORTS], check=True, env={**os.environ, "GIT_PYTHON_REFRESH": "quiet"})
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def median(values: list[float]) -> str:
    return f"{statistics.median(values):.2f} s" if values else "n/a"


def report(args: argparse.Namespace, straight: dict, chaos: dict, imports: float) -> None:
    state: ChaosState = chaos["state"]
    events = state.run.events("start") if state.run else []
    launches = [e["time"] for e in events]
    found = attempts(chaos["timeline"], launches)
    lost = lost_iterations(found) if found else []
    per_iteration = straight["timeline"].iteration_seconds()
    summaries = state.run.events("summary")
    print(f"\nfaults injected ({len(state.injected)}):")
    for n, fault in enumerate(state.injected, 1):
        print(f"  {n:>2}. {fault.injected - state.spawned[0]:7.1f} s  {fault.kind:<15} rank {fault.rank} {fault.note}")
    for (code, at, cause), times in Counter(state.endings).items():
        print(f"  run ended with exit code {code} at fault {at}{f' ({times} times)' if times > 1 else ''}: {cause}")
    print(f"supervisor processes: {len(state.spawned)} ({state.reruns} reruns, {len(state.endings)} unexpected exits)")
    print(
        f"torchrun launches: {len(launches)}; iterations lost: {sum(lost)} (supervisor summaries: "
        f"{sum(s.get('iterations_lost', 0) for s in summaries)})"
    )
    if chaos["wall"] is None:
        print(f"chaos run did not finish: goodput not measured (uninterrupted {straight['wall']:.1f} s)")
        return
    same = chaos["digest"] == straight["digest"]
    print(
        f"final state: step {chaos['digest'][0]}, state_sha256 {chaos['digest'][1][:16]} "
        f"{'EQUALS' if same else 'DIFFERS FROM'} the uninterrupted run's ({straight['digest'][1][:16]})"
    )
    print(f"goodput: {straight['wall']:.1f} s / {chaos['wall']:.1f} s = {straight['wall'] / chaos['wall']:.3f}")

    restarts = found[1:]
    ready = [a.ready - a.launched for a in restarts if a.ready]
    restore = [a.restored - a.ready for a in restarts if a.ready and a.restored]
    first = [a.first - a.restored for a in restarts if a.first and a.restored]
    detection = [a.launched - stopped(chaos["timeline"], before, a.launched) for before, a in itertools.pairwise(found)]
    buckets = {
        "program start-up (launch to ready, first-iteration excess)": sum(ready)
        + sum(max(0.0, f - per_iteration) for f in first),
        "checkpoint restore": sum(restore),
        "wasted progress (iterations lost x straight s/iteration)": sum(lost) * per_iteration,
        "detection and infrastructure recovery": sum(detection),
        "checkpoint save (beyond the uninterrupted run's)": chaos["timeline"].save_seconds()
        - straight["timeline"].save_seconds(),
    }
    extra = chaos["wall"] - straight["wall"]
    buckets["other (the rest; negative: the chaos run trained faster)"] = extra - sum(buckets.values())
    print(f"\nlost time: {extra:.1f} s (chaos - uninterrupted), by ml-goodput-measurement's buckets:")
    for name, seconds in buckets.items():
        print(f"  {name:<60} {seconds:8.1f} s {100 * seconds / extra if extra > 0 else 0:6.1f} %")
    print(
        f"\nwhere a restart goes ({len(restarts)} restarts, medians): launch to ready {median(ready)}, "
        f"restore {median(restore)}, first iteration {median(first)} (a steady one: {per_iteration:.3f} s)"
    )
    steady = (straight["timeline"].median_iteration(), chaos["timeline"].median_iteration())
    print(f"median iteration: uninterrupted run {steady[0]:.3f} s, chaos run {steady[1]:.3f} s (other load)")
    scaled = straight["wall"] * steady[1] / steady[0]
    print(  # the host's speed drifts by 10-20% between two runs of a few minutes here
        f"goodput at the chaos run's training speed (the uninterrupted run scaled by the median iterations, "
        f"{scaled:.1f} s): {scaled / chaos['wall']:.3f}"
    )
    print(f"importing torch, mujoco, rsl_rl, gymnasium alone: {imports:.2f} s (median of 3; a cold restart pays it)")
    print(
        f"restarts with no start-up at all (launch to ready x restarts, {sum(ready):.1f} s less): goodput "
        f"{straight['wall'] / (chaos['wall'] - sum(ready)):.3f}"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--iterations", type=int, default=2500, help="the run's length (234 s, 4 faults at --period 60, on a fast day)"
    )
    parser.add_argument("--period", type=float, default=30.0, help="seconds between faults")
    parser.add_argument("--seed", type=int, default=0, help="draws the faults' order, ranks and time jitter")
    parser.add_argument("--outage", type=float, default=60.0, help="seconds the S3 port refuses in a storage outage")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="a config override for both runs (repeat)"
    )
    parser.add_argument("--max-reruns", type=int, default=10, help="unexpected supervisor exits before giving up")
    parser.add_argument(
        "--max-slowdown", type=float, default=10.0, help="give the chaos run up after this many straight run times"
    )
    parser.add_argument("--keep", action="store_true", help="keep the run directories (printed)")
    args = parser.parse_args()
    sys.stdout.reconfigure(line_buffering=True)  # progress lines show at once, also in a log file
    work = Path(tempfile.mkdtemp(prefix="ftrain-bench-chaos-"))
    bench = Bench(args, work)
    try:
        imports = import_seconds()
        overrides = f" ({' '.join(args.set)})" if args.set else ""
        print(f"uninterrupted run: configs/halfcheetah.yaml{overrides}, 2 ranks, {args.iterations} iterations, S3")
        straight = bench.straight()
        print(f"  {straight['wall']:.1f} s, final step {straight['digest'][0]}")
        print(f"chaos run: a fault every ~{args.period:g} s, seed {args.seed}, outages {args.outage:g} s")
        chaos = bench.chaos(straight["wall"])
        report(args, straight, chaos, imports)
    finally:
        bench.server.stop()
        if args.keep:
            print(f"runs kept in {work}")
        else:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
