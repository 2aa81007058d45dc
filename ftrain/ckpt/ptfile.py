"""A packed state (see ``packing.py``) as a ``torch.save`` file, written without ``torch.save``.

``torch.save`` calls a Python ``persistent_id`` for every object it pickles: most of the time it spends on a
packed state, whose few tensors sit in a tree of a few hundred small objects. Here the plain part is pickled by
the C pickler alone, and the tensors' opcodes, which refer to their storages, are appended by hand. The file is a
zip like the ones ``torch.save`` writes (``data.pkl``, a record per storage in the order the pickle refers to them,
``byteorder`` and ``version``; data aligned to 64 bytes) and ``torch.load(weights_only=True)`` reads it like any
other checkpoint. It declares no ``.format_version``: that would promise miniz's exact record layout (data
descriptors after each record), from which torch may compute offsets instead of reading them from the zip.
"""

from __future__ import annotations

import io
import pickle
import struct
import sys
import zlib

import torch

from ftrain.ckpt import packing

STORAGE_TYPES = {
    torch.float64: "DoubleStorage",
    torch.float32: "FloatStorage",
    torch.float16: "HalfStorage",
    torch.bfloat16: "BFloat16Storage",
    torch.complex128: "ComplexDoubleStorage",
    torch.complex64: "ComplexFloatStorage",
    torch.int64: "LongStorage",
    torch.int32: "IntStorage",
    torch.int16: "ShortStorage",
    torch.int8: "CharStorage",
    torch.uint8: "ByteStorage",
    torch.bool: "BoolStorage",
}
"""How ``torch.save`` names the storage of each dtype; a state with any other dtype goes through ``torch.save``."""
ARCHIVE = "archive"
ALIGNMENT = 64
_ZIP_LIMIT = 0xFFFFFFFF
"""Sizes and offsets above this need zip64 records: such a file goes through ``torch.save``."""
_DOS_DATE = 33  # 1980-01-01, the first date a zip entry can carry


class _TreePickler(pickle.Pickler):
    """Pickles the plain part of a packed state; a tensor or storage in it (one the packing does not reach: in a set,
    as a dict key, inside an object) needs ``torch.save``'s persistent ids. Only objects that are not plain data get
    here, so plain data costs nothing extra."""

    def reducer_override(self, obj: object) -> object:
        if isinstance(obj, (torch.Tensor, torch.UntypedStorage, torch.TypedStorage)):
            raise _NeedsTorchSave
        return NotImplemented


class _NeedsTorchSave(Exception):
    pass


def write(packed: dict) -> bytes | None:
    """The ``torch.save`` file of a packed state (``{"ftrain_packed", "tree", "dtypes", "index", "tensors"}``), or
    None if it needs ``torch.save``: not of the current packing version, a tensor that is not 1-D, contiguous, on
    the CPU, free of autograd and of a dtype in ``STORAGE_TYPES``, a tensor in the plain part, or a file that
    needs zip64 records."""
    if packed.get(packing.PACKED) != packing.VERSION:
        return None
    storages = [packed["index"], *packed["tensors"].values()]  # in the order the pickle refers to them
    if not all(_writable(tensor) for tensor in storages):
        return None
    buffer = io.BytesIO()
    try:
        _TreePickler(buffer, protocol=2).dump({key: packed[key] for key in packed if key not in ("index", "tensors")})
    except _NeedsTorchSave:
        return None
    head = buffer.getbuffer()[:-1]  # PROTO 2 and the dict, left on the stack; STOP comes last
    flats = b"".join(
        _string(name) + _tensor_opcodes(str(key), flat) for key, (name, flat) in enumerate(packed["tensors"].items(), 1)
    )
    tail = b"(" + _string("index") + _tensor_opcodes("0", storages[0]) + _string("tensors") + b"}(" + flats + b"uu."
    records = [
        ("data.pkl", bytes(head) + tail),
        (".storage_alignment", str(ALIGNMENT).encode()),
        ("byteorder", sys.byteorder.encode()),  # the tensors' bytes are the machine's own
        *((f"data/{key}", tensor.view(torch.uint8).numpy().data) for key, tensor in enumerate(storages)),
        ("version", b"3\n"),
    ]
    if sum(len(data) for _, data in records) >= _ZIP_LIMIT // 2:  # headers and padding stay far below the rest
        return None
    return _zip(records)


def _writable(tensor: torch.Tensor) -> bool:
    return (
        tensor.dtype in STORAGE_TYPES
        and tensor.dim() == 1
        and tensor.is_contiguous()
        and tensor.device.type == "cpu"
        and not tensor.requires_grad
    )


def _tensor_opcodes(key: str, value: torch.Tensor) -> bytes:
    """``torch._utils._rebuild_tensor_v2(<storage key>, 0, (numel,), (1,), False, OrderedDict())``, the storage
    given as a persistent id ``("storage", <type>, key, "cpu", numel)``, as ``torch.save`` pickles a tensor."""
    numel = _int(value.numel())
    storage = b"((" + _string("storage") + _global("torch", STORAGE_TYPES[value.dtype]) + _string(key)
    storage += _string("cpu") + numel + b"tQ"  # TUPLE, BINPERSID
    arguments = storage + _int(0) + numel + b"\x85" + _int(1) + b"\x85\x89"  # TUPLE1 (size), TUPLE1 (stride), False
    hooks = _global("collections", "OrderedDict") + b")R"  # OrderedDict()
    return _global("torch._utils", "_rebuild_tensor_v2") + arguments + hooks + b"tR"  # TUPLE, REDUCE


def _string(text: str) -> bytes:
    """BINUNICODE, unmemoized (the memo belongs to the pickled plain part)."""
    data = text.encode()
    return b"X" + struct.pack("<I", len(data)) + data


def _int(number: int) -> bytes:
    return pickle.dumps(number, protocol=2)[2:-1]  # an int is never memoized


def _global(module: str, name: str) -> bytes:
    return f"c{module}\n{name}\n".encode()


def _zip(records: list[tuple[str, bytes | memoryview]]) -> bytes:
    """A zip of stored (uncompressed) records, each one's data aligned to ``ALIGNMENT`` bytes, as torch writes it."""
    parts, directory, offset = [], [], 0
    for name, data in records:
        path = f"{ARCHIVE}/{name}".encode()
        crc, size = zlib.crc32(data), len(data)
        padding = -(offset + 30 + len(path) + 4) % ALIGNMENT
        extra = struct.pack("<HH", 0x4246, padding) + b"Z" * padding  # the padding field torch's writer uses
        fields = struct.pack("<HHHHHIII", 20, 0, 0, 0, _DOS_DATE, crc, size, size)
        parts += [b"PK\x03\x04" + fields + struct.pack("<HH", len(path), len(extra)) + path + extra, data]
        directory.append(
            b"PK\x01\x02"
            + struct.pack("<H", 20)
            + fields
            + struct.pack("<HHHHHII", len(path), 0, 0, 0, 0, 0, offset)
            + path
        )
        offset += 30 + len(path) + len(extra) + size
    central = b"".join(directory)
    end = b"PK\x05\x06" + struct.pack("<HHHHIIH", 0, 0, len(records), len(records), len(central), offset, 0)
    return b"".join([*parts, central, end])
