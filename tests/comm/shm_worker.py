"""Run under torchrun at two ranks or more: what SharedMemoryAllReduce sums (against the rank-ordered sum of what every
rank sent, and against gloo's all_reduce); then the last rank dies, and every other one must notice within the
reducer's timeout. Each rank writes its report to ``OUT.RANK``."""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time

from ftrain.process import imports

with imports():  # as ftrain's own workers import: a cold start at half the CPU
    import torch
    import torch.distributed as dist

    from ftrain.comm import group
    from ftrain.comm.collectives import Comm
    from ftrain.comm.shm_allreduce import PeerLost, SharedMemoryAllReduce


def main(out: str, timeout_s: float) -> None:
    info = group.init(30)
    reducer = SharedMemoryAllReduce(info, capacity=1000, timeout_s=timeout_s)
    generator = torch.Generator().manual_seed(info.rank)
    exact = like_gloo = close = copies = True
    digest = hashlib.sha256()
    for size in (1, 17, 1000):
        for round_ in range(50):
            value = torch.randn(size, generator=generator) * 10.0 ** torch.randint(-6, 6, (size,), generator=generator)
            gathered = [torch.empty_like(value) for _ in range(info.world_size)]
            dist.all_gather(gathered, value)
            by_gloo = value.clone()
            dist.all_reduce(by_gloo)
            result = reducer.all_reduce_(value)
            stacked = torch.stack(gathered)
            exact &= torch.equal(result, stacked.sum(dim=0))  # every rank's slot, summed in rank order
            copies &= torch.equal(reducer.all_gather(gathered[info.rank]), torch.stack(gathered))
            src = int(torch.randint(info.world_size, (1,), generator=torch.Generator().manual_seed(size + round_)))
            copies &= torch.equal(reducer.broadcast_(gathered[info.rank].clone(), src), gathered[src])
            like_gloo &= torch.equal(result, by_gloo)
            # another order of the same sum differs by rounding alone: at most (ranks - 1) ulps of the sum of |x|
            bound = info.world_size * torch.finfo(torch.float32).eps * stacked.abs().sum(dim=0)
            close &= bool(((result - by_gloo).abs() <= bound).all())
            digest.update(result.numpy().tobytes())
            # the iteration's small float64 sums (counts, votes, metrics, reward statistics) through the same memory
            values = (torch.randn(size, dtype=torch.float64, generator=generator) * 1e9).tolist()
            small = torch.tensor(
                Comm(info, list(range(info.world_size)), None, reducer, print).sum_values(values), dtype=torch.float64
            )
            every = [torch.empty(size, dtype=torch.float64) for _ in range(info.world_size)]
            dist.all_gather(every, torch.tensor(values, dtype=torch.float64))
            small_by_gloo = torch.tensor(values, dtype=torch.float64)
            dist.all_reduce(small_by_gloo)
            exact &= torch.equal(small, torch.stack(every).sum(dim=0))  # (a larger one is gathered through gloo)
            exact &= torch.equal(
                small,
                torch.tensor(
                    Comm(info, list(range(info.world_size)), None, None, print).sum_values(values), dtype=torch.float64
                ),
            )
            like_gloo &= torch.equal(small, small_by_gloo)
            digest.update(small.numpy().tobytes())
    wide = torch.arange(reducer.broadcast_capacity, dtype=torch.float32)  # one sender fills every rank's slots
    copies &= torch.equal(reducer.broadcast_(wide + info.rank, info.world_size - 1), wide + info.world_size - 1)
    leftovers = [name for name in os.listdir("/dev/shm") if name.startswith("ftrain-")]
    report = {
        "exact": exact,
        "copies": copies,
        "like_gloo": like_gloo,
        "close": close,
        "digest": digest.hexdigest(),
        "leftovers": leftovers,
    }
    dist.barrier()
    if info.rank == info.world_size - 1:
        os._exit(0)  # dies without a word, between two all-reduces
    started = time.monotonic()
    try:
        reducer.all_reduce_(torch.ones(10))
        report["peer_lost"] = None
    except PeerLost as error:
        report["peer_lost"] = str(error)
    report["seconds"] = time.monotonic() - started
    with open(f"{out}.{info.rank}", "w") as file:
        json.dump(report, file)
    os._exit(0)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
