"""Across hosts: 2 hosts x 2 ranks with ``--delay-ms`` between them against 4 ranks on one host, on the same cores.

At 4 ranks ftrain splits the update into two teams: ranks 0-1 learn the actor, ranks 2-3 the critic. torchrun numbers
a node's ranks consecutively, so on two hosts each team is one host, and the update's per-minibatch meetings (each
team's gradient all-reduce) stay on it, through shared memory. What crosses the hosts is one meeting per phase of
the iteration: the reward statistics, the rollout's gather, the two models' broadcasts, the metrics, each host first
(``ftrain.comm.host_first``: one exchange between the hosts' first ranks). This measures
what that costs: the two-host run's steps/s as a fraction of the one-host run's, each two-host run between two
one-host runs (these machines drift), and the median over ``--rounds``, with each run's phases (ms per iteration,
mean over ranks).

The hosts are the tests' network namespaces (``tests/cluster/netns.py``: each host its own address on one bridge), so
it runs as root. Their latency comes from ``tests/cluster/delay_hub.py``, a process that hands every frame on
``--delay-ms`` late each way, since kernels without netem (this project's machines among them) cannot delay a link:
on a 2-core machine that process shares the cores with the four ranks, so the fraction measured there is a lower
bound of what hosts joined by a real 1 ms link would reach. Every run does the shipped HalfCheetah config's work
with ``env.num_envs=8`` per rank (one global batch of 512 steps, as 1 rank x 32 or 2 x 16).

    sudo .venv/bin/python launch/bench_hosts.py [--delay-ms 1] [--rounds 3] [--iterations 30] [--set KEY=VALUE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "cluster"))  # the tests' bed: netns.py

from ftrain.tools.bench import run_side_by_side, throughput_args
from ftrain.train.phases import PHASES

from netns import DEVICE, Bed, missing

RANKS_PER_HOST = 2


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--delay-ms", type=int, default=1, help="added latency between the hosts, each way")
    parser.add_argument("--rounds", type=int, default=3, help="two-host runs, each between two one-host runs")
    parser.add_argument("--iterations", type=int, default=30, help="timed iterations per run, after 3 of warm-up")
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="config overrides of every run")
    args = parser.parse_args()
    if reason := missing():
        print(f"bench_hosts: {reason}", file=sys.stderr)
        return 2
    overrides = ("env.num_envs=8", *args.set)
    print(f"4 ranks on one host against 2 hosts x 2 ranks, {args.delay_ms} ms between them; {overrides}", flush=True)
    one = [run_side_by_side(args.iterations, [2 * RANKS_PER_HOST], overrides=overrides)[0]]
    two = []
    for _ in range(args.rounds):
        two.append(two_hosts(args.iterations, args.delay_ms, overrides))
        one.append(run_side_by_side(args.iterations, [2 * RANKS_PER_HOST], overrides=overrides)[0])
        around = [run["median_steps_per_s"] for run in one[-2:]]
        line = f"  two hosts {two[-1]['median_steps_per_s']:,.0f} steps/s between one host's {around[0]:,.0f} and "
        print(f"{line}{around[1]:,.0f}", flush=True)
    fractions = [
        run["median_steps_per_s"] / statistics.mean(one[k]["median_steps_per_s"] for k in (i, i + 1))
        for i, run in enumerate(two)
    ]
    print(f"\nsteps/s (median of {args.rounds} rounds); phases in ms per iteration, mean over ranks")
    print(f"{'run':>10} {'steps/s':>9}  " + " ".join(f"{name:>8}" for name in PHASES))
    for name, runs in (("one host", one), ("two hosts", two)):
        phase_ms = {phase: statistics.median(run["phases_ms"][phase] for run in runs) for phase in PHASES}
        speed = statistics.median(run["median_steps_per_s"] for run in runs)
        print(f"{name:>10} {speed:>9,.0f}  " + " ".join(f"{phase_ms[phase]:>8.1f}" for phase in PHASES))
    print(
        f"two hosts / one host: {statistics.median(fractions):.2f} (rounds: {', '.join(f'{f:.2f}' for f in fractions)})"
    )
    return 0


def two_hosts(iterations: int, delay_ms: int, overrides: tuple[str, ...]) -> dict:
    """One run on two network-namespace hosts, ``RANKS_PER_HOST`` ranks each, ``delay_ms`` apart: its JSON report."""
    bed = Bed(2)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "throughput.json"
        try:
            bed.start(delay_ms=delay_ms)
            nodes = []
            for host in range(2):
                rendezvous = [
                    "--nnodes=2",
                    f"--nproc-per-node={RANKS_PER_HOST}",
                    f"--node-rank={host}",
                    "--rdzv-backend=c10d",
                    f"--rdzv-endpoint={bed.address(0)}:29533",
                    f"--rdzv-conf=is_host={int(host == 0)}",  # the hosts share one hostname: say which one serves
                    f"--local-addr={bed.address(host)}",
                ]
                train = throughput_args(iterations, out, str(Path(tmp) / "run"), Path(tmp) / "logs", overrides)
                command = [*bed.launcher(host), sys.executable, "-m", "torch.distributed.run", *rendezvous]
                command += ["-m", "ftrain", "train", *train]
                env = {**os.environ, "OMP_NUM_THREADS": "1", "GLOO_SOCKET_IFNAME": DEVICE}
                with (Path(tmp) / f"host-{host}.log").open("w") as log:
                    nodes.append(subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT))
            if any(node.wait(timeout=1800) for node in nodes):
                raise RuntimeError(f"the two-host run failed:\n{(Path(tmp) / 'host-0.log').read_text()[-3000:]}")
            return json.loads(out.read_text())
        finally:
            bed.stop()


if __name__ == "__main__":
    sys.exit(main())
