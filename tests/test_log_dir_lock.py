"""One run per log directory: a run on one node and the nodes of a run on several, claimed and given back in random
orders, exclude each other as the rule says, and a refusal names exactly the holders that stand in the way."""

from __future__ import annotations

import contextlib
import random
import re
import shutil

import pytest

from ftrain.config import storage_key
from ftrain.errors import UserError
from ftrain.log_dir_lock import STORAGE_FILE, claim_log_dir

STORAGE = "/a/run"
"""The storage of the runs that claim (``storage_key``)."""
NODES = (None, 0, 1, 2)
"""Who claims: a run on one node (None), or node N of a run on several."""


def admitted(held: dict[str, int | None], node: int | None) -> bool:
    """The rule: a run on one node holds the directory alone; nodes of several share it, one holder per number."""
    if node is None:
        return not held
    return all(other is not None and other != node for other in held.values())


def blocking(held: dict[str, int | None], node: int | None) -> set[str]:
    """The holders a refused claim of ``node`` must name."""
    if node is None:
        return set(held)
    single = {name for name, other in held.items() if other is None}
    return single or {name for name, other in held.items() if other == node}


def test_random_claims_and_releases_follow_the_rule_and_refusals_name_the_live_holders(tmp_path, capsys):
    schedules, claims, refusals = 200, 0, 0
    for schedule in range(schedules):
        rng = random.Random(schedule)
        log_dir = tmp_path / f"logs{schedule}"
        held: dict[str, int | None] = {}
        stacks: dict[str, contextlib.ExitStack] = {}
        for step in range(14):
            if held and rng.random() < 0.4:  # give one back
                name = rng.choice(sorted(held))
                stacks.pop(name).close()
                del held[name]
                continue
            node, name = rng.choice(NODES), f"claim{step}"
            stack = contextlib.ExitStack()
            claims += 1
            try:
                stack.enter_context(claim_log_dir(log_dir, node, name, STORAGE))
            except UserError as refused:
                refusals += 1
                assert not admitted(held, node), (schedule, step, held, node)
                named = set(re.findall(r"(claim\d+) pid \d+ on ", str(refused)))
                assert named == blocking(held, node), (schedule, step, held, node, str(refused))
                assert str(refused).endswith("or give this one a log directory of its own with log_dir=DIR")
                continue
            assert admitted(held, node), (schedule, step, held, node)
            held[name], stacks[name] = node, stack
        for stack in stacks.values():
            stack.close()
    print(f"{schedules} schedules: {claims} claims, {refusals} refused, every one as the rule says")
    assert refusals > schedules  # the schedules do reach the refusals they check
    assert claims - refusals > schedules


def test_a_lock_file_that_cannot_be_taken_is_one_line(tmp_path):
    (tmp_path / "run.lock").mkdir()  # not a file: as a lock on a file system without locks, or not ours to write
    for node in (None, 0):
        refused = pytest.raises(UserError, match=rf"^log directory {tmp_path} cannot be held \({tmp_path}/run.lock: ")
        with refused, claim_log_dir(tmp_path, node, "supervisor", STORAGE):
            pass


def test_a_log_directory_holds_one_storages_records_however_that_storage_is_spelt(tmp_path, monkeypatch):
    """A log directory taken by a run keeps to its storage: every spelling of it is admitted (relative, with a
    trailing slash, ``file://``, through a link), another storage is refused with one line naming both and the
    records, even after the first run ended, and nothing is written; until the directory holds records, another
    storage may take it (a run refused before it trained); a local storage's own directory stays its own after a
    move."""
    storage, other = tmp_path / "run", tmp_path / "other"
    storage.mkdir()
    (tmp_path / "link").symlink_to(storage)
    logs = tmp_path / "logs"
    monkeypatch.chdir(tmp_path)
    spellings = ["run", "run/", f"{storage}/", f"file://{storage}", "link", "./link/"]
    for spelling in random.Random(0).sample(spellings, len(spellings)):
        with claim_log_dir(logs, None, "supervisor", storage_key(spelling)):
            pass
    assert (logs / STORAGE_FILE).read_text() == f"{storage}\n"
    with claim_log_dir(logs, None, "supervisor", storage_key(str(other))):  # no records yet: anyone's
        pass
    with claim_log_dir(logs, None, "supervisor", storage_key(str(storage))):  # and the first run's again
        for record in ("metrics.csv", "config.yaml"):
            (logs / record).write_text("its records\n")
    for node in (None, 1):
        with pytest.raises(UserError) as refused, claim_log_dir(logs, node, "supervisor", storage_key(str(other))):
            pass
        assert str(refused.value) == (
            f"log directory {logs} holds the records of the run on {storage} (its metrics.csv, config.yaml): give the "
            f"run on {other} a log directory of its own with log_dir=DIR (if that storage has moved to {other}, delete "
            f"{logs / STORAGE_FILE} first)"
        )
    assert (logs / STORAGE_FILE).read_text() == f"{storage}\n"
    with claim_log_dir(storage, None, "supervisor", storage_key(str(storage))):  # its default log directory
        pass
    made_in_them = claim_log_dir(logs, None, "supervisor", storage_key(str(logs)))  # a storage made in its records
    with pytest.raises(UserError, match=f"holds the records of the run on {storage} "), made_in_them:
        pass
    assert (logs / STORAGE_FILE).read_text() == f"{storage}\n"
    copy = tmp_path / "copy"  # copied with its steps: its own too, while the original is still there
    shutil.copytree(storage, copy)
    (copy / "checkpoints").mkdir()
    with claim_log_dir(copy, None, "supervisor", storage_key(str(copy))):
        pass
    storage.rename(other)  # moved: its own directory is still its own
    with claim_log_dir(other, None, "supervisor", storage_key(str(other))):
        pass
    assert (other / STORAGE_FILE).read_text() == f"{other}\n"
