"""Checkpoint cost at 2 ranks on the HalfCheetah config, to local disk and to a local S3 API server (moto).

For the default policy and a large one (``policy.hidden_dims=[2048,2048,1024]``, ~150 MB of state with Adam's
moments), measured side by side in one run: training throughput with checkpoints at the default
``checkpoint.interval`` and at every iteration against none, how long the loop is blocked per save (async: the
snapshot handed to the writer thread; sync: the whole save inline) and a plain ``torch.save`` of the same state.
Targets: at the default interval, checkpoints cost <= 1% of throughput to local disk and <= 3% to S3; for the large
policy the loop is blocked <= 10% of the synchronous save.

These machines are noisy (run-to-run throughput varies by 10% and more), so the cases run in ``--rounds`` rounds,
each round every case once, side by side; a cost is the median over rounds of the ratio within a round. For S3 it
also prints the CPU time the local S3 server (moto, a Python process on the same cores) spends per save: work that
a real S3 does on other machines, yet here takes cores from training.

    .venv/bin/python launch/bench_checkpoint.py [--policies default large] [--rounds 3]
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

from ftrain.config import CheckpointConfig
from ftrain.procfs import cpu_seconds
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


POLICIES = {"default": ((), 40), "large": (("policy.hidden_dims=[2048,2048,1024]",), 12)}
"""Overrides and timed iterations of each policy size (a large-policy iteration takes seconds)."""
DEFAULT_INTERVAL = CheckpointConfig().interval


def cases() -> dict[str, tuple[str | None, tuple[str, ...]]]:
    """name -> (storage kind, overrides): none, then per storage async at the default interval and every iteration,
    and sync at every iteration (its blocking is a whole save)."""
    found: dict[str, tuple[str | None, tuple[str, ...]]] = {"none": (None, ())}
    for where in ("local", "s3"):
        found[f"{where} async/{DEFAULT_INTERVAL}"] = (where, (f"checkpoint.interval={DEFAULT_INTERVAL}",))
        found[f"{where} async/1"] = (where, ("checkpoint.interval=1",))
        found[f"{where} sync/1"] = (where, ("checkpoint.interval=1", "checkpoint.async_save=false"))
    return found


def measure(policy: str, rounds: int, bucket: str, s3_env: dict, moto_pid: int, tmp: str) -> dict[str, list[dict]]:
    extra, n = POLICIES[policy]
    results: dict[str, list[dict]] = {name: [] for name in cases()}
    for round_ in range(rounds):
        for name, (where, overrides) in cases().items():
            folder = f"{policy}-{name.replace(' ', '-').replace('/', '-')}-{round_}"
            storage = {None: None, "local": f"{tmp}/{folder}", "s3": f"{bucket}/{folder}"}[where]
            before = cpu_seconds(moto_pid)
            result = run_ftrain(n, 2, storage, (*extra, *overrides), s3_env if where == "s3" else None)
            saves = WARMUP + n if "checkpoint.interval=1" in overrides else -(-(WARMUP + n) // DEFAULT_INTERVAL)
            result["blocking_median_s"] = statistics.median(result["blocking_s"] or [math.nan])
            result["moto_cpu_per_save_s"] = (cpu_seconds(moto_pid) - before) / saves
            for key in ("steps_per_s", "median_steps_per_s"):
                result[f"{key}/none"] = result[key] / results["none"][-1][key] if where else 1.0
            results[name].append(result)
        print(f"{policy}: round {round_ + 1}/{rounds} done", file=sys.stderr, flush=True)
    return results


def report(policy: str, results: dict[str, list[dict]]) -> None:
    def median(name: str, key: str) -> float:
        return statistics.median(result[key] for result in results[name])

    def spread(name: str, key: str) -> str:
        ratios = [result[key] for result in results[name]]
        return f"{min(ratios):.0%}-{max(ratios):.0%}"

    print(f"\n{policy} policy ({POLICIES[policy][1]} timed iterations per case)")
    print(
        f"{'case':<15} {'steps/s':>9} {'vs none':>8} {'rounds':>9} {'median iter.':>13} "
        f"{'blocked/save (median, max)':>28} {'moto CPU/save':>14}"
    )
    for name, (where, _) in cases().items():
        blocking = [seconds for result in results[name] for seconds in result["blocking_s"]]
        blocked = f"{statistics.median(blocking) * 1e3:8.2f} ms {max(blocking) * 1e3:8.2f} ms" if blocking else "-"
        moto = f"{median(name, 'moto_cpu_per_save_s') * 1e3:8.1f} ms" if where == "s3" else "-"
        print(
            f"{name:<15} {median(name, 'steps_per_s'):>9,.0f} {median(name, 'steps_per_s/none'):>7.1%} "
            f"{spread(name, 'steps_per_s/none'):>9} {median(name, 'median_steps_per_s/none'):>12.1%} {blocked:>28} "
            f"{moto:>14}"
        )
    plain = median("none", "torch_save_s")
    print(f"plain torch.save of the same state (rank 0, local file): {plain * 1e3:.2f} ms")
    for where in ("local", "s3"):
        blocked = median(f"{where} async/1", "blocking_median_s")
        whole = median(f"{where} sync/1", "blocking_median_s")
        cost = 1 - median(f"{where} async/{DEFAULT_INTERVAL}", "steps_per_s/none")
        every = 1 - median(f"{where} async/1", "steps_per_s/none")
        print(
            f"{where}: cost at the default interval {cost:.1%} (every iteration {every:.1%}); async blocks "
            f"{blocked * 1e3:.1f} ms = {blocked / whole:.1%} of a sync save ({whole * 1e3:.1f} ms), "
            f"{blocked / plain:.1%} of a plain torch.save"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policies", nargs="+", choices=sorted(POLICIES), default=sorted(POLICIES))
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    with moto_server() as (bucket, s3_env, moto_pid), tempfile.TemporaryDirectory() as tmp:
        measured = {policy: measure(policy, args.rounds, bucket, s3_env, moto_pid, tmp) for policy in args.policies}
    for policy, results in measured.items():
        report(policy, results)
    print(
        "\n(vs none: throughput over the timed window, median over rounds of the ratio within a round; rounds: the"
        "\n lowest and highest of those ratios; median iter.: the same from the median iteration time, which bursts"
        "\n of other work on the machine disturb less)"
    )


if __name__ == "__main__":
    main()
