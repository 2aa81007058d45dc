"""Run under torchrun as several nodes on this machine (each torchrun agent a host): what the host-first collectives
gather, broadcast and sum, against gloo's own over all ranks, and the same through a layout with the hosts' ranks
interleaved; then the last rank dies, and every other one must notice within the timeout. Each rank writes its
report to ``OUT.RANK``."""

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
    from ftrain.comm.host_first import HostFirst, build_collectives, hosts_of_ranks


def main(out: str, timeout_s: float) -> None:
    info = group.init(timeout_s)
    hosts = hosts_of_ranks(info)
    collectives = build_collectives(info, 1000, timeout_s, hosts)
    interleaved = HostFirst(info, [str(rank % 2) for rank in range(info.world_size)], 1000, timeout_s)
    report = {"hosts": hosts, "kind": type(collectives).__name__}
    for name, ours in (("torchrun", collectives), ("interleaved", interleaved)):
        report[name] = check(ours, info)
    os.environ["GROUP_RANK"] = str(info.rank)  # a node rank per rank, against torchrun's count of ranks per node
    report["disagreeing_hosts"] = hosts_of_ranks(info)
    dist.barrier()
    if info.rank == info.world_size - 1:
        os._exit(0)  # dies without a word, between two collectives
    started = time.monotonic()
    try:
        collectives.all_gather(torch.ones(10))
        report["peer_lost"] = None
    except Exception as error:  # what the survivor learns: its shared memory's PeerLost, or gloo's error
        report["peer_lost"] = f"{type(error).__name__}: {error}"[:300]
    report["seconds"] = time.monotonic() - started
    with open(f"{out}.{info.rank}", "w") as file:
        json.dump(report, file)
    os._exit(0)


def check(collectives: HostFirst, info: group.RankInfo) -> dict:
    """Gathers and broadcasts bit for bit as gloo's, the small float64 sums in rank order, the all-reduce to
    rounding; a digest of every result (the same on every rank)."""
    generator = torch.Generator().manual_seed(info.rank)
    gathers = broadcasts = sums = reduced = True
    digest = hashlib.sha256()
    for size in (1, 17, 1000):
        for round_ in range(20):
            value = torch.randn(size, generator=generator) * 10.0 ** torch.randint(-6, 6, (size,), generator=generator)
            every = [torch.empty_like(value) for _ in range(info.world_size)]
            dist.all_gather(every, value)
            gathered = collectives.all_gather(value)
            gathers &= torch.equal(gathered, torch.stack(every))
            src = (size + round_) % info.world_size
            broadcasts &= torch.equal(collectives.broadcast_(value.clone(), src), every[src])
            by_gloo = value.clone()
            dist.all_reduce(by_gloo)
            result = collectives.all_reduce_(value.clone())
            bound = info.world_size * torch.finfo(torch.float32).eps * torch.stack(every).abs().sum(dim=0)
            reduced &= bool(((result - by_gloo).abs() <= bound).all())
            values = (torch.randn(size, dtype=torch.float64, generator=generator) * 1e9).tolist()
            small = torch.tensor(
                Comm(info, list(range(info.world_size)), None, collectives, print).sum_values(values),
                dtype=torch.float64,
            )
            every64 = [torch.empty(size, dtype=torch.float64) for _ in range(info.world_size)]
            dist.all_gather(every64, torch.tensor(values, dtype=torch.float64))
            if 2 * size <= collectives.capacity:  # (a larger one goes through gloo)
                sums &= torch.equal(small, torch.stack(every64).sum(dim=0))
            for tensor in (gathered, result, small):
                digest.update(tensor.numpy().tobytes())
    wide = torch.arange(collectives.broadcast_capacity, dtype=torch.float32)  # as wide as a broadcast goes
    last = info.world_size - 1
    broadcasts &= torch.equal(collectives.broadcast_(wide + info.rank, last), wide + last)
    return {
        "gathers": gathers,
        "broadcasts": broadcasts,
        "sums": sums,
        "reduced": reduced,
        "digest": digest.hexdigest(),
    }


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
