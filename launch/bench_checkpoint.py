"""Checkpoint cost at 2 ranks on the HalfCheetah config, to local disk and to a local S3 API server (moto).

Prints, measured side by side in one run: how long the training loop is blocked per save (async and sync), the
time of a plain ``torch.save`` of the same state, and training throughput with a checkpoint every iteration
against none. Targets: async blocking <= 10% of sync; checkpointing every iteration costs <= 5% of throughput.

    .venv/bin/python launch/bench_checkpoint.py [--iterations 40]
"""

from __future__ import annotations

import argparse
import contextlib
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import uuid

from ftrain.bench import run_ftrain

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
        yield f"s3://{bucket}", env
    finally:
        proc.terminate()
        proc.wait()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=40)
    args = parser.parse_args()
    n = args.iterations
    every = ("checkpoint.interval=1",)
    sync = (*every, "checkpoint.async_save=false")
    with moto_server() as (bucket, s3_env), tempfile.TemporaryDirectory() as tmp:
        cases = {
            "none": run_ftrain(n, 2),
            "local async": run_ftrain(n, 2, f"{tmp}/a", every),
            "local sync": run_ftrain(n, 2, f"{tmp}/s", sync),
            "s3 async": run_ftrain(n, 2, f"{bucket}/a", every, s3_env),
            "s3 sync": run_ftrain(n, 2, f"{bucket}/s", sync, s3_env),
        }
    base = cases["none"]["steps_per_s"]
    print(f"{'case':<12} {'steps/s':>9} {'vs none':>8} {'blocked/save (median, max)':>28}")
    for name, result in cases.items():
        blocking = result["blocking_s"]
        blocked = f"{statistics.median(blocking) * 1e3:8.2f} ms {max(blocking) * 1e3:8.2f} ms" if blocking else "-"
        print(f"{name:<12} {result['steps_per_s']:>9,.0f} {result['steps_per_s'] / base:>7.1%} {blocked:>28}")
    print(f"plain torch.save of the same state (rank 0, local file): {cases['none']['torch_save_s'] * 1e3:.2f} ms")
    for where in ("local", "s3"):
        ratio = statistics.median(cases[f"{where} async"]["blocking_s"]) / statistics.median(
            cases[f"{where} sync"]["blocking_s"]
        )
        cost = 1 - cases[f"{where} async"]["steps_per_s"] / base
        print(f"{where}: async blocking = {ratio:.1%} of sync; checkpoint every iteration costs {cost:.1%} throughput")


if __name__ == "__main__":
    main()
