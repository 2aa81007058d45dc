"""W&B's offline transaction log (``<dir>/offline-run-*-<id>/run-<id>.wandb``) read as the SDK writes it: a 7-byte
``:W&B`` header, then a LevelDB-style log (32 KiB blocks of chunks, each with a 7-byte header: checksum, length,
type) of ``Record`` protobufs. The SDK ships no reader; ftrain reads it to learn which steps an offline run holds on
disk (W&B flushes it every so often, so a killed process loses what it had not flushed)."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

BLOCK = 32768
HEADER = 7
FULL, FIRST, MIDDLE, LAST = 1, 2, 3, 4


def records(path: Path) -> Iterator:
    """The ``wandb_internal_pb2.Record``s of one file, up to the first torn or unreadable one."""
    from google.protobuf.message import DecodeError
    from wandb.proto import wandb_internal_pb2

    data = path.read_bytes()
    if data[:4] != b":W&B":
        return
    pos, pending = HEADER, b""
    while pos + HEADER <= len(data):
        left = BLOCK - pos % BLOCK
        if left < HEADER:  # a block's tail too short for a chunk header is padding
            pos += left
            continue
        _, length, kind = struct.unpack("<IHB", data[pos : pos + HEADER])
        chunk, pos = data[pos + HEADER : pos + HEADER + length], pos + HEADER + length
        if kind not in (FULL, FIRST, MIDDLE, LAST) or len(chunk) < length:
            return
        pending = chunk if kind in (FULL, FIRST) else pending + chunk
        if kind in (FULL, LAST):
            record = wandb_internal_pb2.Record()
            try:
                record.ParseFromString(pending)
            except DecodeError:
                return
            yield record


def offline_files(wandb_dir: Path, run_id: str) -> list[Path]:
    """The transaction logs of every offline start of run ``run_id``, oldest first."""
    return sorted(wandb_dir.glob(f"offline-run-*-{run_id}/run-{run_id}.wandb"))


def last_offline_step(wandb_dir: Path, run_id: str) -> int:
    """The last step any offline start of ``run_id`` wrote to disk (-1: none)."""
    steps = (
        record.history.step.num
        for path in offline_files(wandb_dir, run_id)
        for record in records(path)
        if record.WhichOneof("record_type") == "history"
    )
    return max(steps, default=-1)
