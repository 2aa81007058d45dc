"""ftrain.ckpt.ptfile: packed states written as torch.save files without torch.save, read back by torch.load."""

import io
import math
import struct
import zipfile

import torch

from ftrain.ckpt import packing, ptfile
from ftrain.ckpt.format import decode, encode

from helpers import assert_same


def every_dtype_state() -> dict:
    generator = torch.Generator().manual_seed(3)
    tensors = {str(dtype): (torch.randn(4, 3, generator=generator) * 100).to(dtype) for dtype in ptfile.STORAGE_TYPES}
    return {
        "tensors": tensors,
        "empty": torch.zeros(0, 5),
        "scalar": torch.tensor(2.5, dtype=torch.float64),
        "strided": torch.arange(12.0).reshape(3, 4).t(),
        "plain": [1, -7, 2**70, -(2**65), 0.5, math.inf, None, True, "ünïcode", (1, "two"), {"k": [[]]}],
    }


def test_a_packed_state_loads_back_bitwise_with_weights_only():
    state = every_dtype_state()
    packed = packing.pack(state)
    data = ptfile.write(packed)
    assert data is not None
    loaded = torch.load(io.BytesIO(data), weights_only=True)
    assert_same(packing.unpack(loaded), state)
    assert packing.digest(loaded) == packing.digest(packed)
    assert encode(packed) == data  # what checkpoints are written with


def test_the_file_is_a_valid_zip_with_aligned_records_like_torch_saves():
    packed = packing.pack(every_dtype_state())
    archive = zipfile.ZipFile(io.BytesIO(ptfile.write(packed)))
    assert archive.testzip() is None  # every CRC-32 matches
    reference = io.BytesIO()
    torch.save(packed, reference)
    own = {"archive/.data/serialization_id", "archive/.format_version"}  # see the module docstring for the latter
    expected = set(zipfile.ZipFile(reference).namelist()) - own
    assert set(archive.namelist()) == expected
    raw = archive.fp.getvalue()
    for info in archive.infolist():
        name_length, extra_length = struct.unpack_from("<HH", raw, info.header_offset + 26)
        assert (info.header_offset + 30 + name_length + extra_length) % ptfile.ALIGNMENT == 0, info.filename


def test_the_file_loads_memory_mapped(tmp_path):
    state = every_dtype_state()
    path = tmp_path / "state.pt"
    path.write_bytes(ptfile.write(packing.pack(state)))
    loaded = torch.load(path, weights_only=True, mmap=True)
    assert_same(packing.unpack(loaded), state)


def test_loads_that_compute_offsets_or_only_read_metadata_work(tmp_path, monkeypatch):
    """torch.load on the meta device, with its debug checks, and with offsets computed from the zip's layout."""
    from torch.utils.serialization import config

    state = every_dtype_state()
    path = tmp_path / "state.pt"
    path.write_bytes(ptfile.write(packing.pack(state)))
    meta = torch.load(path, weights_only=True, map_location="meta")
    assert meta["tensors"]["float32"].device.type == "meta"
    monkeypatch.setenv("TORCH_SERIALIZATION_DEBUG", "1")
    with config.patch({"load.calculate_storage_offsets": True}):
        assert_same(packing.unpack(torch.load(path, weights_only=True, mmap=True)), state)
        assert_same(packing.unpack(torch.load(path, weights_only=True)), state)


def test_states_it_does_not_take_go_through_torch_save():
    odd = packing.pack({"x": torch.arange(4).to(torch.uint16), "y": torch.ones(2)})
    assert ptfile.write(odd) is None
    assert_same(decode(encode(odd)), packing.unpack(odd))
    assert ptfile.write({packing.PACKED: 1, "tree": {}, "tensors": {}}) is None  # version 1
    grad = packing.pack({"y": torch.ones(2)})
    grad["tensors"]["float32"].requires_grad_()
    assert ptfile.write(grad) is None
    hidden = packing.pack({"y": torch.ones(2)})
    hidden["tree"]["keys"] = {(torch.zeros(1), 1): "a tensor the packing does not reach"}
    assert ptfile.write(hidden) is None
    assert isinstance(encode(hidden), bytes)
