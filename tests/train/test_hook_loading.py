"""A user's hook that cannot be had, whatever the reason (the import, the module, the class, its kwargs, its
constructor): one line naming the hook and the fix, where it raised when its own code did, and never a traceback or
an exit that a supervisor would take for a crash and restart."""

from __future__ import annotations

import subprocess
import sys

import pytest

from ftrain.errors import UserError, module_missing
from ftrain.train.hooks import Hook, load_hook

from helpers import SMOKE, child_env

MODULE = """
from ftrain.train.hooks import Hook


class Fine(Hook):
    def __init__(self, every=1):
        self.every = every


class Raising(Hook):
    def __init__(self, **kwargs):
        raise ValueError("bad hook arg")


class NotAHook:
    pass
"""


@pytest.mark.parametrize(
    ("target", "kwargs", "expected"),
    [
        ("userhooks_absent:Fine", {}, "hook target 'userhooks_absent:Fine' cannot be imported (No module named"),
        ("userhooks:Missing", {}, "hook target 'userhooks:Missing' cannot be imported (module 'userhooks' has no"),
        (
            "userhooks_broken:Fine",
            {},
            "hook target 'userhooks_broken:Fine' cannot be imported: ZeroDivisionError: float division by zero "
            "(userhooks_broken.py, line 2): fix the module",
        ),
        (  # the module is there; an import of its own is not (it was told to fix the import path)
            "userhooks_needs:Fine",
            {},
            "hook target 'userhooks_needs:Fine' cannot be imported: ModuleNotFoundError: No module named "
            "'nonexistent_module_xyz' (userhooks_needs.py, line 1): fix the module",
        ),
        ("userhooks:Fine", {"evry": 2}, "hook 'userhooks:Fine' rejects its kwargs (got an unexpected keyword argument"),
        (
            "userhooks:Raising",
            {},
            "hook 'userhooks:Raising' cannot be made: ValueError: bad hook arg (userhooks.py, line 12): fix the hook "
            "or its kwargs",
        ),
        ("userhooks:NotAHook", {}, "hook 'userhooks:NotAHook' is not a subclass of ftrain.train.hooks.Hook"),
    ],
)
def test_a_hook_that_cannot_be_had_is_one_line_naming_it(tmp_path, monkeypatch, target, kwargs, expected) -> None:
    (tmp_path / "userhooks.py").write_text(MODULE)
    (tmp_path / "userhooks_broken.py").write_text("import math\nmath.pi / 0\n")
    (tmp_path / "userhooks_needs.py").write_text("import nonexistent_module_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)  # where the file is named from
    for name in ("userhooks", "userhooks_broken", "userhooks_needs"):  # not another case's, imported before
        monkeypatch.delitem(sys.modules, name, raising=False)
    with pytest.raises(UserError) as refused:
        load_hook(target, kwargs)
    assert str(refused.value).startswith(expected) and "\n" not in str(refused.value), str(refused.value)
    fine = load_hook("userhooks:Fine", {"every": 3})
    assert isinstance(fine, Hook) and fine.every == 3


@pytest.mark.parametrize(
    ("hook", "said"),
    [
        (
            '{target: "userhooks_absent:Fine"}',
            "hook target 'userhooks_absent:Fine' cannot be imported (No module named 'userhooks_absent'): fix the "
            "import path",
        ),
        ('{target: "os:getcwd"}', "hook 'os:getcwd' is not a subclass of ftrain.train.hooks.Hook: make it one, or "),
        (
            '{target: "ftrain.train.hooks:CsvHook", kwargs: {b: 1}}',
            "hook 'ftrain.train.hooks:CsvHook' rejects its kwargs (got an unexpected keyword argument 'b'): fix its "
            "kwargs",
        ),
    ],
)
@pytest.mark.parametrize("command", ["train", "supervise"])
def test_a_hook_that_cannot_be_had_is_refused_before_the_run_takes_its_storage(tmp_path, command, hook, said) -> None:
    """Refused after the topology line and the storage's lease, it was two lines and left a lease, a lock and
    storage.txt in a storage that held nothing; under ``supervise``, the workers were launched to find it. Now one
    line, and no storage made: ``train`` checks the hooks' modules, classes and kwargs itself, ``supervise`` in a
    child."""
    storage = tmp_path / "run"
    argv = [sys.executable, "-m", "ftrain", command, SMOKE, "--storage", str(storage), f"hooks=[{hook}]"]
    result = subprocess.run(argv, cwd=tmp_path, env=child_env(), capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and result.stdout == "", result.stdout
    assert result.stderr.startswith(f"ftrain: error: {said}") and result.stderr.count("\n") == 1, result.stderr
    assert not storage.exists()


def test_a_module_is_missing_only_where_it_or_a_package_above_it_is_not_there() -> None:
    """What the one-line refusals of hooks and env modules tell apart: "fix the import path" against "fix the
    module" (an import of the module's own failed)."""
    cases = {
        ("userenv", "userenv"): True,
        ("userenv.robots", "userenv"): True,  # its package is not there
        ("userenv_x", "userenv"): False,  # another module that userenv_x imports
        ("userenv", "numpyy"): False,
        ("userenv.robots", "userenv.robots.arm"): False,
    }
    for (name, missing), expected in cases.items():
        assert module_missing(ModuleNotFoundError(name=missing), name) is expected, (name, missing)
    assert not module_missing(ImportError("cannot import name 'x'"), "userenv")
    print(f"{len(cases) + 1} cases checked")
