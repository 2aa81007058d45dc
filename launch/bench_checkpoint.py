"""Checkpoint cost at 2 ranks on the HalfCheetah config, to local disk and to a local S3 API server (moto).

Prints, measured side by side in one run: how long the training loop is blocked per save (async and sync), the
time of a plain ``torch.save`` of the same state, and training throughput with a checkpoint every iteration
against none. Targets: async blocking <= 10% of sync; checkpointing every iteration costs <= 5% of throughput.

These machines are noisy (run-to-run throughput varies by 10% and more), so the cases run in ``--rounds`` rounds,
each round every case once, side by side; a cost is the median over rounds of the ratio within a round. For S3 it
also prints the CPU time the local S3 server (moto, a Python process on the same cores) spends per save: work that
a real S3 does on other machines, yet here takes cores from training.

    .venv/bin/python launch/bench_checkpoint.py [--iterations 40] [--rounds 3]
"""

from __future__ import annotations

import argparse
import contextlib
import math
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import uuid

from ftrain.supervise.procfs import cpu_seconds
from ftrain.tools.bench import WARMUP, run_ftrain

KEY, SECRET = "bench-key", "bench-secret"


@contextlib.contextmanager
def moto_server():
    """A real S3 API server on 127.0.0.1 with a fresh bucket; yields (bucket URL, environment for the runs)."""
    import boto3

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    endpoint = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 30
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.5):
                break
            if time.monotonic() > deadline:
                raise RuntimeError("moto server did not start")
            time.sleep(0.05)
        bucket = f"bench-{uuid.uuid4().hex[:8]}"
        client = boto3.client(
            "s3", endpoint_url=endpoint, aws_access_key_id=KEY, aws_secret_access_key=SECRET, region_name="us-east-1"
        )
        client.create_bucket(Bucket=bucket)
        env = {
            "AWS_ENDPOINT_URL": endpoint,
            "AWS_ACCESS_KEY_ID": KEY,
            "AWS_SECRET_ACCESS_KEY": SECRET,
            "AWS_DEFAULT_REGION": "us-east-1",
        }
        yield f"s3://{bucket}", env, proc.pid
    finally:
        proc.terminate()
        proc.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    n = args.iterations
    every = ("checkpoint.interval=1",)
    sync = (*every, "checkpoint.async_save=false")
    cases = {
        "none": (None, ()),
        "local async": ("local", every),
        "local sync": ("local", sync),
        "s3 async": ("s3", every),
        "s3 sync": ("s3", sync),
    }
    results: dict[str, list[dict]] = {name: [] for name in cases}
    with moto_server() as (bucket, s3_env, moto_pid), tempfile.TemporaryDirectory() as tmp:
        for round_ in range(args.rounds):
            for name, (where, overrides) in cases.items():
                folder = name.replace(" ", "-") + f"-{round_}"
                storage = {None: None, "local": f"{tmp}/{folder}", "s3": f"{bucket}/{folder}"}[where]
                before = cpu_seconds(moto_pid)
                result = run_ftrain(n, 2, storage, overrides, s3_env if where == "s3" else None)
                result["blocking_median_s"] = statistics.median(result["blocking_s"] or [math.nan])
                result["moto_cpu_per_save_s"] = (cpu_seconds(moto_pid) - before) / (WARMUP + n)
                for key in ("steps_per_s", "median_steps_per_s"):
                    result[f"{key}/none"] = result[key] / results["none"][-1][key] if where else 1.0
                results[name].append(result)
            print(f"round {round_ + 1}/{args.rounds} done", file=sys.stderr, flush=True)

    def median(name: str, key: str) -> float:
        return statistics.median(result[key] for result in results[name])

    def spread(name: str, key: str) -> str:
        ratios = [result[key] for result in results[name]]
        return f"{min(ratios):.0%}-{max(ratios):.0%}"

    print(
        f"{'case':<12} {'steps/s':>9} {'vs none':>8} {'rounds':>9} {'median iter.':>13} "
        f"{'blocked/save (median, max)':>28} {'moto CPU/save':>14}"
    )
    for name, (where, _) in cases.items():
        blocking = [seconds for result in results[name] for seconds in result["blocking_s"]]
        blocked = f"{statistics.median(blocking) * 1e3:8.2f} ms {max(blocking) * 1e3:8.2f} ms" if blocking else "-"
        moto = f"{median(name, 'moto_cpu_per_save_s') * 1e3:8.1f} ms" if where == "s3" else "-"
        print(
            f"{name:<12} {median(name, 'steps_per_s'):>9,.0f} {median(name, 'steps_per_s/none'):>7.1%} "
            f"{spread(name, 'steps_per_s/none'):>9} {median(name, 'median_steps_per_s/none'):>12.1%} {blocked:>28} "
            f"{moto:>14}"
        )
    print("(vs none: throughput over the timed window, median over rounds of the ratio within a round; rounds: the")
    print(" lowest and highest of those ratios; median iter.: the same from the median iteration time, which bursts")
    print(" of other work on the machine disturb less)")
    print(f"plain torch.save of the same state (rank 0, local file): {median('none', 'torch_save_s') * 1e3:.2f} ms")
    for where in ("local", "s3"):
        ratio = median(f"{where} async", "blocking_median_s") / median(f"{where} sync", "blocking_median_s")
        cost = 1 - median(f"{where} async", "steps_per_s/none")
        cost_median = 1 - median(f"{where} async", "median_steps_per_s/none")
        print(
            f"{where}: async blocking = {ratio:.1%} of sync; checkpoint every iteration costs {cost:.1%} throughput "
            f"({cost_median:.1%} by median iteration time)"
        )


if __name__ == "__main__":
    main()
