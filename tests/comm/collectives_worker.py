"""Run under torchrun with 2 ranks: ftrain's object collectives carry JSON, so a peer can send data, never code."""

from __future__ import annotations

import json
import pickle
import sys

from ftrain.process import exit_fast, imports

with imports():  # as ftrain's own workers import: a cold start at half the CPU
    import torch
    import torch.distributed as dist

    from ftrain.comm import group


class Payload:
    """What a pickle-based collective carries, and runs code to rebuild on the receiver."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))


def main(out: str, marker: str) -> None:
    info = group.init(timeout_s=30)
    gathered = group.all_gather_object({"rank": info.rank, "files": {"a.pt": [3, "ff"]}}, info)
    broadcast = group.broadcast_object({"kind": "committed", "step": 4} if info.is_main else None, info)
    report = {"gathered": gathered, "broadcast": broadcast}
    try:
        group.all_gather_object(Payload(marker), info)  # refused by every sender before anything is sent
    except TypeError as exc:
        report["refused"] = str(exc)
    # a hostile rank 0 sends a pickle in the wire format (length, then bytes): rank 1 must not unpickle it
    if info.is_main:
        data = torch.frombuffer(bytearray(pickle.dumps(Payload(marker))), dtype=torch.uint8)
        dist.broadcast(torch.tensor([data.numel()], dtype=torch.int64), src=0)
        dist.broadcast(data, src=0)
    else:
        try:
            group.broadcast_object(None, info)
        except ValueError as exc:  # json's errors (and UnicodeDecodeError) are ValueErrors
            report["hostile"] = type(exc).__name__
    with open(f"{out}.{info.rank}", "w") as file:
        json.dump(report, file)
    group.shutdown()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
    exit_fast(0)  # without the interpreter's teardown of torch, as ftrain's workers end
