"""Packed state: the tensors of a nested state moved into one flat tensor per dtype, and a digest over it.

Encoding, pickling and walking a state cost per object, whatever its size: ``torch.save`` spends about 15 µs per
tensor, and a Python call per list, dict, string or number. A training state has many small tensors (optimizer
moments, normalizers, per-env buffers), so packed it encodes ten times faster: one flat tensor per dtype, one
marker string per tensor in the tree, and the dtypes and shapes of all tensors in one index tensor. Packing copies
every tensor, so it is also the snapshot a background save works from; :meth:`Layout.fill` can copy straight into
memory that the save helper shares. The packed form is plain data, loadable with ``torch.load(weights_only=True)``;
:func:`ftrain.checkpoint.decode` unpacks it::

    {"ftrain_packed": 2,
     "tree": <the state, each tensor replaced by the string TENSOR>,
     "dtypes": ["float32", "int64", ...],
     "index": <int64: for each tensor in tree order, its dtype's position in "dtypes", ndim, then its shape>,
     "tensors": {"float32": <flat tensor>, "int64": <flat tensor>, ...}}

Each tensor is the next run of its dtype's flat tensor, in tree order (dict insertion order). Version 1, which
wrote ``{"__tensor__": [dtype, offset, shape]}`` in place of each tensor, still unpacks.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Iterator

import torch
from torch._utils import _flatten_dense_tensors  # each tensor flattened and all concatenated, in one C++ call

PACKED = "ftrain_packed"
VERSION = 2
TENSOR = "\x00ftrain-tensor"
"""The place of a tensor in a packed tree."""
TENSOR_V1 = "__tensor__"

FLATTEN_LIMIT = 1 << 22
"""Bytes of one dtype up to which :meth:`Layout.fill` flattens its tensors in one C++ call into a temporary and
copies that into place: for small tensors a Python call each costs more than the extra copy, for large ones the
copy costs more (they are concatenated straight into place then)."""

Allocate = Callable[[torch.dtype, int], torch.Tensor]
"""Where the flat tensor of a dtype goes: ``allocate(dtype, numel)`` returns an empty 1-D tensor of that size."""


class Layout:
    """The packed tree of a state and the tensors each flat tensor is made of, before anything is copied."""

    def __init__(self, state: dict) -> None:
        self.parts: dict[torch.dtype, list[torch.Tensor]] = {}
        self.numels: dict[torch.dtype, int] = {}
        self._positions: dict[torch.dtype, int] = {}
        self._index: list[int] = []
        self.tree = self._walk(state)

    @property
    def nbytes(self) -> int:
        """The bytes of the packed tensors (index included), each of which :meth:`fill` allocates."""
        return sum(numel * dtype.itemsize for dtype, numel in self.numels.items()) + 8 * len(self._index)

    @property
    def allocations(self) -> int:
        return len(self.numels) + 1

    def fill(self, allocate: Allocate | None = None) -> dict:
        """The packed state, its flat tensors from ``allocate`` (new tensors if None): a copy training cannot change."""
        tensors = {}
        with torch.no_grad():  # parameters require grad; a copy needs no graph
            for dtype, parts in self.parts.items():
                numel = self.numels[dtype]
                flat = torch.empty(numel, dtype=dtype) if allocate is None else allocate(dtype, numel)
                if numel * dtype.itemsize <= FLATTEN_LIMIT:
                    flat.copy_(_flatten_dense_tensors(parts))
                else:
                    torch.cat([part.reshape(-1) for part in parts], out=flat)
                tensors[dtype_name(dtype)] = flat
        index = torch.tensor(self._index, dtype=torch.int64)
        if allocate is not None:
            index = allocate(torch.int64, index.numel()).copy_(index)
        dtypes = [dtype_name(dtype) for dtype in self._positions]  # the order the index refers to
        return {PACKED: VERSION, "tree": self.tree, "dtypes": dtypes, "index": index, "tensors": tensors}

    def _walk(self, value: object) -> object:
        if isinstance(value, dict):  # OrderedDict (state dicts) and other mappings too: saved as plain dicts
            return {key: self._walk(item) for key, item in value.items()}
        if isinstance(value, (list, tuple)):
            return type(value)(self._walk(item) for item in value)
        if isinstance(value, torch.Tensor):
            dtype = value.dtype
            position = self._positions.setdefault(dtype, len(self._positions))
            self._index += (position, value.dim(), *value.shape)
            self.parts.setdefault(dtype, []).append(value)
            self.numels[dtype] = self.numels.get(dtype, 0) + value.numel()
            return TENSOR
        if type(value) is str and value == TENSOR:
            raise ValueError(f"the state holds the string {TENSOR!r}, which marks a tensor in a packed state")
        return value


def pack(state: dict) -> dict:
    """The packed form of ``state`` (dicts, lists, tuples, tensors and plain values): a copy training cannot change."""
    return Layout(state).fill()


def is_packed(state: object) -> bool:
    return isinstance(state, dict) and PACKED in state


def unpack(packed: dict) -> dict:
    """The state :func:`pack` was given (its tensors are views into the flat ones); ValueError if malformed."""
    if packed.get(PACKED) == 1:
        return _unpack_v1(packed)
    places = _places(packed)

    def walk(value: object) -> object:
        kind = type(value)
        if kind is dict:
            return {key: walk(item) for key, item in value.items()}
        if kind is list or kind is tuple:
            return kind(walk(item) for item in value)
        if kind is str and value == TENSOR:
            dtype, offset, shape = next(places, (None, 0, ()))
            if dtype is None:
                raise ValueError("the packed tree has more tensors than its index")
            return tensors[dtype][offset : offset + math.prod(shape)].view(shape)
        return value

    tensors = packed["tensors"]
    if not isinstance(packed.get("tree"), dict):
        raise ValueError("the packed tree is not a dict")
    state = walk(packed["tree"])
    if next(places, None) is not None:
        raise ValueError("the packed index has more tensors than the tree")
    return state


def digest(packed: dict, key: str | None = None) -> str:
    """SHA-256 over the structure, values, dtypes, shapes and bytes of a packed state, or of its top-level entry
    ``key``, without unpacking: equal iff bitwise equal (for states built the same way: dict order counts)."""
    places = list(_places(packed))
    tree = packed["tree"]
    if key is not None:  # the entry's tensors are the run of places after those of the entries before it
        keys = list(tree)
        start = sum(_count_tensors(tree[other]) for other in keys[: keys.index(key)])
        tree = tree[key]
        places = places[start : start + _count_tensors(tree)]
    hasher = hashlib.sha256(repr(tree).encode())
    hasher.update(repr([(dtype, shape) for dtype, _, shape in places]).encode())
    extents: dict[str, list[int]] = {}
    for dtype, offset, shape in places:
        extent = extents.setdefault(dtype, [offset, offset])
        extent[1] = offset + math.prod(shape)
    tensors = packed["tensors"]
    for dtype, (low, high) in sorted(extents.items()):
        hasher.update(tensors[dtype][low:high].view(torch.uint8).numpy())
    return hasher.hexdigest()


def _places(packed: dict) -> Iterator[tuple[str, int, list[int]]]:
    """(dtype, offset in its flat tensor, shape) of each tensor, in tree order; ValueError if they do not fit."""
    if packed.get(PACKED) != VERSION:
        raise ValueError(f"packed format {packed.get(PACKED)!r} is not one this ftrain reads (1 and {VERSION})")
    dtypes, index, tensors = packed.get("dtypes"), packed.get("index"), packed.get("tensors")
    if not (
        isinstance(dtypes, list)
        and all(isinstance(name, str) for name in dtypes)
        and isinstance(index, torch.Tensor)
        and index.dtype == torch.int64
        and index.dim() == 1
        and isinstance(tensors, dict)
        and all(_is_flat(tensors.get(name), name) for name in dtypes)
    ):
        raise ValueError("packed 'dtypes', 'index' or 'tensors' are malformed")
    numbers = index.tolist()
    offsets = dict.fromkeys(dtypes, 0)
    cursor = 0
    places = []
    while cursor < len(numbers):
        if cursor + 2 > len(numbers):
            raise ValueError("the packed index ends in the middle of an entry")
        position, ndim = numbers[cursor : cursor + 2]
        shape = numbers[cursor + 2 : cursor + 2 + ndim]
        if not 0 <= position < len(dtypes) or not 0 <= ndim == len(shape) or min(shape, default=0) < 0:
            raise ValueError(f"packed index entry {len(places)} (dtype {position}, ndim {ndim}) is malformed")
        cursor += 2 + ndim
        dtype = dtypes[position]
        offset = offsets[dtype]
        offsets[dtype] = offset + math.prod(shape)
        if offsets[dtype] > tensors[dtype].numel():
            raise ValueError(f"packed tensor {len(places)} ({dtype}, shape {shape}) does not fit the packed tensors")
        places.append((dtype, offset, shape))
    return iter(places)


def _is_flat(tensor: object, name: str) -> bool:
    return isinstance(tensor, torch.Tensor) and tensor.dim() == 1 and dtype_name(tensor.dtype) == name


def _count_tensors(value: object) -> int:
    if isinstance(value, dict):
        return sum(_count_tensors(item) for item in value.values())
    if isinstance(value, (list, tuple)):
        return sum(_count_tensors(item) for item in value)
    return int(type(value) is str and value == TENSOR)


def dtype_name(dtype: torch.dtype) -> str:
    """``torch.float32`` -> ``"float32"``: how packed files name dtypes."""
    return str(dtype).removeprefix("torch.")


def _unpack_v1(packed: dict) -> dict:
    tensors = packed.get("tensors")
    if not isinstance(tensors, dict) or not all(isinstance(t, torch.Tensor) for t in tensors.values()):
        raise ValueError("packed 'tensors' is not a mapping of dtype to tensor")

    def walk(value: object) -> object:
        if isinstance(value, dict):
            if TENSOR_V1 in value:
                return _tensor_v1(tensors, value[TENSOR_V1])
            return {key: walk(item) for key, item in value.items()}
        if isinstance(value, (list, tuple)):
            return type(value)(walk(item) for item in value)
        return value

    return walk(packed.get("tree"))


def _tensor_v1(tensors: dict[str, torch.Tensor], ref: object) -> torch.Tensor:
    try:
        dtype, offset, shape = ref
        numel = math.prod(shape)
        flat = tensors[dtype]
        if offset < 0 or offset + numel > flat.numel():
            raise ValueError
        return flat[offset : offset + numel].view(shape)
    except (TypeError, ValueError, KeyError, RuntimeError):
        raise ValueError(f"packed tensor reference {ref!r} does not fit the packed tensors") from None
