"""A packed state (see ``packing.py``) as the bytes of a ``torch.save`` file, written without ``torch.save``.

``torch.save`` calls a Python ``persistent_id`` for every object it pickles: most of the time it spends on a
packed state, whose few tensors sit in a tree of a few hundred small objects. Here the plain part is pickled by
the C pickler alone, and the tensors' opcodes, which refer to their storages, are appended by hand: the result is
what ``torch.save`` writes (a zip of ``data.pkl``, one record per storage, and the version records, data aligned
to 64 bytes), and ``torch.load(weights_only=True)`` reads it like any other checkpoint.
"""

from __future__ import annotations

import pickle
import struct
import zlib

import torch

from ftrain import packing

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


def can_write(packed: dict) -> bool:
    """Whether :func:`write` takes ``packed``: a packed state of the current version whose tensors are 1-D,
    contiguous and of dtypes in ``STORAGE_TYPES``, small enough to need no zip64 records."""
    if packed.get(packing.PACKED) != packing.VERSION:
        return False
    tensors = [packed["index"], *packed["tensors"].values()]
    return (
        all(tensor.dtype in STORAGE_TYPES and tensor.dim() == 1 and tensor.is_contiguous() for tensor in tensors)
        and sum(tensor.nbytes for tensor in tensors) < _ZIP_LIMIT // 2  # the rest: the pickled tree
    )


def write(packed: dict) -> bytes:
    """The ``torch.save`` file of a packed state (``{"ftrain_packed", "tree", "dtypes", "index", "tensors"}``)."""
    storages: list[torch.Tensor] = []

    def tensor(value: torch.Tensor) -> bytes:
        storages.append(value)
        return _tensor_opcodes(str(len(storages) - 1), value)

    plain = {key: value for key, value in packed.items() if key not in ("index", "tensors")}
    head = pickle.dumps(plain, protocol=2)[:-1]  # PROTO 2 and the dict, left on the stack; no STOP yet
    flats = b"".join(_string(name) + tensor(flat) for name, flat in packed["tensors"].items())
    tail = b"(" + _string("index") + tensor(packed["index"]) + _string("tensors") + b"}(" + flats + b"uu."
    records = [
        ("data.pkl", head + tail),
        (".format_version", b"1"),
        (".storage_alignment", str(ALIGNMENT).encode()),
        ("byteorder", b"little"),
        *((f"data/{key}", value.view(torch.uint8).numpy().data) for key, value in enumerate(storages)),
        ("version", b"3\n"),
    ]
    return _zip(records)


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
