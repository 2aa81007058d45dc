"""Packed state: a lossless, weights_only-loadable copy with one tensor per dtype, and the state digest."""

from __future__ import annotations

import io

import pytest
import torch

from ftrain import checkpoint, packing


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


def assert_same(actual: object, expected: object) -> None:
    assert type(actual) is type(expected)
    if isinstance(expected, torch.Tensor):
        assert actual.dtype == expected.dtype and actual.shape == expected.shape
        assert torch.equal(actual, expected)
    elif isinstance(expected, dict):
        assert list(actual) == list(expected)
        for key in expected:
            assert_same(actual[key], expected[key])
    elif isinstance(expected, (list, tuple)):
        assert len(actual) == len(expected)
        for a, e in zip(actual, expected, strict=True):
            assert_same(a, e)
    else:
        assert actual == expected


def test_round_trip_through_a_file_is_lossless_with_one_tensor_per_dtype() -> None:
    state = sample_state()
    data = checkpoint.encode(packing.pack(state))
    raw = torch.load(io.BytesIO(data), weights_only=True)
    assert sorted(raw["tensors"]) == ["bool", "float32", "float64", "int64", "uint8"]
    assert_same(checkpoint.decode(data), state)


def test_pack_is_a_snapshot_that_training_cannot_change() -> None:
    state = sample_state()
    expected = state["model"]["weight"].clone()
    packed = packing.pack(state)
    state["model"]["weight"].add_(1.0)
    state["episodes"][0].append("later")
    unpacked = packing.unpack(packed)
    assert torch.equal(unpacked["model"]["weight"], expected)
    assert unpacked["episodes"][0] == [1.5, 10]


def test_a_reference_outside_the_packed_tensors_is_corrupt_not_loaded() -> None:
    packed = packing.pack(sample_state())
    packed["tree"]["counts"][packing.TENSOR][1] = 10**6
    with pytest.raises(checkpoint.CorruptCheckpoint, match="does not fit the packed tensors"):
        checkpoint.decode(checkpoint.encode(packed), "common.pt")


def test_digest_is_equal_iff_bitwise_equal() -> None:
    state = sample_state()
    reordered = dict(reversed(list(state.items())))
    assert packing.digest(reordered) == packing.digest(state)

    nudged = sample_state()
    assert packing.digest(nudged) == packing.digest(state)
    bias = nudged["model"]["bias"]
    bias[0] = torch.nextafter(bias[0], torch.tensor(1.0))  # one bit in the last place
    assert packing.digest(nudged) != packing.digest(state)

    reshaped = sample_state()
    reshaped["counts"] = reshaped["counts"].reshape(3, 1)  # same bytes, another shape
    assert packing.digest(reshaped) != packing.digest(state)
    retyped = {"x": torch.zeros(2, dtype=torch.int32)}
    assert packing.digest(retyped) != packing.digest({"x": torch.zeros(2, dtype=torch.float32)})
