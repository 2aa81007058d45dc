"""Packed state: a lossless, weights_only-loadable copy with one tensor per dtype, and the state digest."""

from __future__ import annotations

import io

import pytest
import torch

from ftrain.ckpt import packing
from ftrain.ckpt.format import CorruptCheckpoint, decode, encode

from helpers import assert_same


def sample_state() -> dict:
    weight = torch.arange(12, dtype=torch.float32).reshape(3, 4)
    return {
        "model": {"weight": weight, "weight_t": weight.t(), "bias": torch.tensor([0.5, -1.5])},
        "optimizer": {
            "state": {0: {"step": torch.tensor(7.0), "exp_avg": torch.linspace(-1, 1, 12).reshape(3, 4)}},
            "lr": 1e-3,
        },
        "rng": torch.Generator().manual_seed(0).get_state(),
        "counts": torch.tensor([1, 2, 3], dtype=torch.int64),
        "mask": torch.tensor([True, False]),
        "empty": torch.empty(0, 5, dtype=torch.float64),
        "episodes": [[1.5, 10], (2.5, 20)],
        "name": "HalfCheetah-v5",
        "nothing": None,
    }


def test_round_trip_through_a_file_is_lossless_with_one_tensor_per_dtype() -> None:
    state = sample_state()
    data = encode(packing.pack(state))
    raw = torch.load(io.BytesIO(data), weights_only=True)
    assert sorted(raw["tensors"]) == ["bool", "float32", "float64", "int64", "uint8"]
    assert_same(decode(data), state)


def test_pack_is_a_snapshot_that_training_cannot_change() -> None:
    state = sample_state() | {"parameter": torch.nn.Parameter(torch.ones(2, dtype=torch.float16))}
    expected = state["model"]["weight"].clone()
    packed = packing.pack(state)
    state["model"]["weight"].add_(1.0)
    state["mask"].logical_not_()  # the only tensor of its dtype
    with torch.no_grad():
        state["parameter"].mul_(3.0)  # a parameter (requires grad), the only one of its dtype
    state["episodes"][0].append("later")
    unpacked = packing.unpack(packed)
    assert torch.equal(unpacked["model"]["weight"], expected)
    assert torch.equal(unpacked["mask"], torch.tensor([True, False]))
    assert torch.equal(unpacked["parameter"], torch.ones(2, dtype=torch.float16))
    assert not unpacked["parameter"].requires_grad
    assert unpacked["episodes"][0] == [1.5, 10]


def test_large_tensors_are_concatenated_straight_into_place(monkeypatch) -> None:
    monkeypatch.setattr(packing, "FLATTEN_LIMIT", 0)
    state = sample_state()
    unpacked = packing.unpack(packing.pack(state | {"parameter": torch.nn.Parameter(torch.ones(3))}))
    assert torch.equal(unpacked.pop("parameter"), torch.ones(3))
    assert_same(unpacked, state)


@pytest.mark.parametrize(
    ("damage", "reason"),
    [
        (lambda packed: packed["index"].__setitem__(2, 10**6), "does not fit the packed tensors"),
        (lambda packed: packed.__setitem__("index", packed["index"][:-3]), "index ends in the middle|malformed"),
        (lambda packed: packed.__setitem__("index", packed["index"].view(1, -1)), "malformed"),
        (lambda packed: packed["index"].__setitem__(0, 99), "entry 0 .* is malformed"),
        (lambda packed: packed["tree"].__setitem__("extra", packing.TENSOR), "more tensors than its index"),
        (lambda packed: packed["tree"].__setitem__("counts", 3), "more tensors than the tree"),
        (lambda packed: packed["dtypes"].reverse(), "does not fit|malformed"),
        (lambda packed: packed["tensors"].__setitem__("float32", torch.zeros(40, dtype=torch.int32)), "malformed"),
        (lambda packed: packed.__setitem__("tree", None), "not a dict"),
        (lambda packed: packed.__setitem__("ftrain_packed", 3), "packed format 3 is not one this ftrain reads"),
    ],
)
def test_a_packed_state_whose_index_does_not_fit_is_corrupt_not_loaded(damage, reason) -> None:
    packed = packing.pack(sample_state())
    damage(packed)
    with pytest.raises(CorruptCheckpoint, match=reason):
        decode(encode(packed), "common.pt")


def test_the_marker_string_in_a_state_is_refused_at_pack_time() -> None:
    with pytest.raises(ValueError, match="marks a tensor"):
        packing.pack({"hooks": {"note": packing.TENSOR}})


def test_version_1_packing_still_loads_and_is_checked() -> None:
    flat = torch.tensor([1.0, 2.0, 3.0, 4.0])
    packed = {
        "ftrain_packed": 1,
        "tree": {"w": {"__tensor__": ["float32", 1, [3]]}, "n": 2},
        "tensors": {"float32": flat},
    }
    state = decode(encode(packed))
    assert state["n"] == 2 and torch.equal(state["w"], flat[1:])
    packed["tree"]["w"]["__tensor__"][1] = 2  # three elements from offset 2 do not fit four
    with pytest.raises(CorruptCheckpoint, match="does not fit the packed tensors"):
        decode(encode(packed), "common.pt")


def digest(state: dict, key: str | None = None) -> str:
    return packing.digest(packing.pack(state), key)


def test_digest_is_equal_iff_bitwise_equal() -> None:
    state = sample_state()
    assert digest(sample_state()) == digest(state)

    nudged = sample_state()
    bias = nudged["model"]["bias"]
    bias[0] = torch.nextafter(bias[0], torch.tensor(1.0))  # one bit in the last place
    assert digest(nudged) != digest(state)

    reshaped = sample_state()
    reshaped["counts"] = reshaped["counts"].reshape(3, 1)  # same bytes, another shape
    assert digest(reshaped) != digest(state)
    retyped = {"x": torch.zeros(2, dtype=torch.int32)}
    assert digest(retyped) != digest({"x": torch.zeros(2, dtype=torch.float32)})
    renamed = sample_state()
    renamed["name"] = "Ant-v5"
    assert digest(renamed) != digest(state)


def test_digest_of_one_entry_sees_only_that_entry() -> None:
    state = sample_state()
    other = sample_state()
    other["optimizer"]["state"][0]["exp_avg"] += 1  # float32 like "model", right after it in the flat tensor
    other["counts"] += 1
    other["rng"] = torch.zeros_like(other["rng"])
    other["episodes"].append([3.5, 30])
    assert digest(other, "model") == digest(state, "model")
    assert digest(other) != digest(state)

    other["model"]["weight"][0, 0] = -1.0
    assert digest(other, "model") != digest(state, "model")
