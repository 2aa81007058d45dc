"""A bare torchrun worker for tests/supervise/test_elastic.py: all-reduces in a loop, prints its world, and on
SIGTERM (torchrun's agent restarting it, e.g. when a node joins) agrees with the others to exit 0."""

from __future__ import annotations

import os
import signal
import sys
import time

import torch
import torch.distributed as dist

stop = False


def request_stop(*_: object) -> None:
    global stop
    stop = True


signal.signal(signal.SIGTERM, request_stop)
dist.init_process_group("gloo")
rank, world = dist.get_rank(), dist.get_world_size()
print(f"world {world} rank {rank}", flush=True)
for _ in range(int(os.environ.get("ROUNDS", "600"))):
    vote = torch.tensor([float(stop)])
    dist.all_reduce(vote)
    if vote.item() > 0:
        sys.exit(0)
    time.sleep(0.05)
