"""A rank's arithmetic: recorded in every manifest, and a resume on another one says that the run continues, not
bit for bit. ``ATEN_CPU_CAPABILITY=default`` stands in for another CPU: ATen's kernels then take the path of a CPU
without vector instructions, as torch's own dispatch would there."""

from __future__ import annotations

import re

import pytest

from ftrain.ckpt.arithmetic import PINS, by_rank, change, describe

from helpers import final_manifest, run_train

OTHER_CPU = {"ATEN_CPU_CAPABILITY": "default"}


def test_a_moved_rank_is_named_with_what_it_runs_on_now_and_before() -> None:
    saved = by_rank(["cpu A", "cpu A", "cpu B"])
    assert saved == {"cpu A": [0, 1], "cpu B": [2]}
    assert change(saved, ["cpu A", "cpu A", "cpu B"]) is None
    assert change(saved, ["cpu A", "cpu B", "cpu B", "cpu C"]) == "rank 1: cpu B (was cpu A)"  # rank 3 is new
    assert change(saved, ["cpu C", "cpu C"]) == "ranks 0, 1: cpu C (was cpu A)"
    assert change(None, ["cpu A"]) is None  # a manifest of an ftrain that did not record it


def test_the_description_names_the_cpu_its_kernels_the_pins_and_the_versions(monkeypatch) -> None:
    for name in PINS:
        monkeypatch.delenv(name, raising=False)
    plain = describe()
    assert re.fullmatch(r".+, \w+ kernels; torch [^,]+, mujoco [^,]+, numpy .+", plain), plain
    monkeypatch.setenv("MKL_CBWR", "COMPATIBLE")
    assert describe() == plain.replace(" kernels; ", " kernels; MKL_CBWR=COMPATIBLE; ")


@pytest.mark.slow
def test_a_resume_on_other_arithmetic_says_so_and_trains_other_bits(tmp_path, reference_run, reference_state) -> None:
    reference = final_manifest(reference_run(8))
    assert list(reference["arithmetic"].values()) == [[0, 1]], reference["arithmetic"]
    (here,) = reference["arithmetic"]

    storage = tmp_path / "run"
    run_train(storage, "iterations=4", ranks=2)
    result = run_train(storage, "iterations=8", ranks=2, env=OTHER_CPU)

    assert "resumed from step 4 " in result.stdout, result.stdout
    moved = re.search(
        r"step 4 was trained on other arithmetic \(ranks 0, 1: (.+) \(was (.+)\)\): the run continues", result.stdout
    )
    assert moved and moved[2] == here and "ATEN_CPU_CAPABILITY=default" in moved[1], result.stdout
    final = final_manifest(storage)
    assert final["arithmetic"] == {moved[1]: [0, 1]}
    assert final["state_sha256"] != reference_state(8)  # what the line says: the same run, other bits
