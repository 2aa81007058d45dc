"""The architecture as the code must keep it: packages import one way, no cycles, small modules, a torch-free
supervisor."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

from helpers import REPO

PACKAGE = REPO / "ftrain"
LAYERS = {
    "__main__": {"entry", "cli", "warm", "proctitle"},
    "entry": {"errors", "process", "terminal"},
    "cli": {
        "supervise",
        "train",
        "policy",
        "tools",
        "ckpt",
        "config",
        "values",
        "errors",
        "errorfile",
        "progress",
        "lifeline",
        "redact",
        "proctitle",
        "process",
        "terminal",
    },
    "tools": {"train", "ckpt", "config", "values", "errors", "files", "progress"},
    "supervise": {
        "ckpt",
        "config",
        "errors",
        "errorfile",
        "heartbeat",
        "identity",
        "redact",
        "procfs",
        "proctitle",
        "progress",
        "lifeline",
        "log_dir_lock",
        "terminal",
        "warm",
    },
    "train": {
        "policy",
        "ckpt",
        "comm",
        "config",
        "errors",
        "errorfile",
        "files",
        "heartbeat",
        "track",
        "redact",
        "procfs",
        "terminal",
    },
    "track": {"config", "values", "errors", "files", "redact"},
    "policy": {"ckpt", "config", "errors", "progress"},
    "ckpt": {
        "comm",
        "config",
        "values",
        "errors",
        "files",
        "heartbeat",
        "identity",
        "lifeline",
        "log_dir_lock",
        "procfs",
        "progress",
        "redact",
    },
    "comm": {"errors", "procfs"},
    "torchrun": {"config", "entry", "errors", "errorfile", "files", "lifeline", "process", "proctitle", "terminal"},
    "config": {"values", "errors", "redact", "log_dir_lock"},
    "values": {"errors", "redact"},
    "heartbeat": {"files"},
    "log_dir_lock": {"errors", "files"},
    "identity": set(),
    "warm": {"errors", "lifeline", "proctitle", "process"},
    "lifeline": {"procfs", "heartbeat"},
    "procfs": set(),
    "errorfile": {"files"},
    "files": set(),
    "redact": set(),
    "progress": set(),
    "errors": {"errorfile", "terminal"},
    "terminal": set(),
    "proctitle": set(),
    "process": {"errors"},
}
"""What each package (or top-level module) of ftrain may import from the others."""
LAZY_IMPORTS_ALLOWED = {"ftrain.entry", "ftrain.__main__", "ftrain.torchrun", "ftrain.cli", "ftrain.tools.bench"}
"""The commands' entries import inside the stop guard (``ftrain/entry.py``), so that a stop while they import is one
line; the CLI imports each subcommand's package when it runs, so that ``ftrain --help`` starts fast; the benchmark
imports what each case measures (torch, rsl-rl, SB3, the envs) in that case, so that ``launch/bench_*.py --help`` does
too."""


def modules() -> dict[str, Path]:
    return {
        ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__"): path
        for path in sorted(PACKAGE.rglob("*.py"))
    }


def ftrain_imports(path: Path) -> list[tuple[str, bool]]:
    """``(module, at module level)`` of every ``ftrain`` import in ``path`` (those for type checking alone too)."""
    tree = ast.parse(path.read_text())
    found = []

    def visit(node: ast.AST, top: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                visit(child, False)
            elif isinstance(child, ast.ImportFrom) and child.module and child.module.split(".")[0] == "ftrain":
                for alias in child.names:
                    name = f"{child.module}.{alias.name}"
                    found.append((name if name in modules() else child.module, top))
            elif isinstance(child, ast.Import):
                found.extend((a.name, top) for a in child.names if a.name.split(".")[0] == "ftrain")
            else:
                visit(child, top)

    visit(tree, True)
    return found


def layer(module: str) -> str:
    return module.split(".")[1] if "." in module else "ftrain"


def test_packages_import_one_way() -> None:
    wrong = []
    for module, path in modules().items():
        for imported, _ in ftrain_imports(path):
            source, target = layer(module), layer(imported)
            if source != target and target != "ftrain" and target not in LAYERS[source]:
                wrong.append(f"{module} imports {imported}")
    assert not wrong, "imports against the layering:\n" + "\n".join(wrong)


def test_no_import_cycles_and_no_imports_hidden_in_functions() -> None:
    graph = {module: set() for module in modules()}
    hidden = []
    for module, path in modules().items():
        for imported, top in ftrain_imports(path):
            if not top and module not in LAZY_IMPORTS_ALLOWED:
                hidden.append(f"{module} imports {imported} inside a function")
            if top and imported in graph and imported != module:  # a type's import too: a circle of types is one
                graph[module].add(imported)
    assert not hidden, "\n".join(hidden)

    cycles = []
    state: dict[str, str] = {}

    def walk(module: str, trail: list[str]) -> None:
        state[module] = "open"
        for imported in sorted(graph[module]):
            if state.get(imported) == "open":
                cycles.append(" -> ".join([*trail[trail.index(imported) :], imported]))
            elif imported not in state:
                walk(imported, [*trail, imported])
        state[module] = "done"

    for module in sorted(graph):
        if module not in state:
            walk(module, [module])
    assert not cycles, "import cycles:\n" + "\n".join(cycles)


def test_every_package_says_what_lives_there_and_what_it_may_import() -> None:
    for init in PACKAGE.glob("*/__init__.py"):
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and "May import: " in doc, f"{init.relative_to(REPO)} needs a docstring with 'May import: '"
        listed = re.sub(r"\([^)]*\)", "", doc.split("May import: ", 1)[1].split(".", 1)[0])  # its first sentence
        said = {name.strip() for name in listed.replace("\n", " ").split(",")}
        package = init.parent.name
        assert said == LAYERS[package], f"{init.relative_to(REPO)} says it may import {sorted(said)}: {LAYERS[package]}"


def test_the_supervisor_imports_no_torch_mujoco_or_rsl_rl() -> None:
    """In a fresh interpreter: the supervisor must start fast and survive a broken training install."""
    supervise = [m for m in modules() if m.startswith("ftrain.supervise")]
    code = (
        f"import sys; import ftrain.cli; {'; '.join(f'import {m}' for m in supervise)}; "
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'mujoco', 'rsl_rl', 'gymnasium', 'numpy'}))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert result.stdout.strip() == "[]", f"the supervisor imported {result.stdout.strip()}"
