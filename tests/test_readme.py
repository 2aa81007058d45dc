"""The commands the README and ``docs/`` show. The README's "Using it" and docs/own-robot.md's walk-through run, every
line as a reader runs it, in order, in a scratch directory laid out like the repository (``configs/``, ``launch/``,
``examples/``, ``.venv/``); each line in a shell that ran the block's ``source`` lines first. Every other ``ftrain``
command of the docs (several nodes, etcd, SLURM, trackers: they need machines, servers or accounts the suite does not
have in that form) is parsed by ftrain's own parser and its config loaded, and every script they name exists; the
tests in ``tests/cluster`` and ``tests/track`` run their equivalents.

Two things differ from a reader's run, so that the block takes minutes instead of hours:

- training lines (``ftrain train``, ``ftrain supervise``, under torchrun or not) get ``SMOKE_SIZED`` appended: a
  quarter of configs/smoke.yaml's work per iteration. Run lengths, checkpoint intervals and retention stay as
  written, so the steps the block names are the steps a reader's run keeps;
- the benchmarks (``ftrain bench``, ``python launch/bench_*.py``) only show their ``--help``.

``PYTHONPATH`` points at this checkout, so the virtualenv's ``ftrain`` and ``python`` run the code under test (a no-op
when the virtualenv installed ftrain from this checkout, as ``launch/setup.sh`` does).
"""

from __future__ import annotations

import itertools
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import REPO, child_env

SMOKE_SIZED = (
    "env.num_envs=2",
    "env.kwargs={max_episode_steps: 50}",
    "num_steps_per_env=8",
    "policy.hidden_dims=[16,16]",
    "algorithm.num_learning_epochs=1",
    "algorithm.num_mini_batches=1",
    "algorithm.gradient_length=8",  # distillation: one truncated back-propagation per rollout of 8 steps
    "log.tensorboard=false",
)
"""Overrides that come after the line's own and so win: 16 steps per rank and iteration, one update of one batch."""
OUTPUT_OPTIONS = ("-o", "--video")
SELF_WARNINGS = re.compile(r"learning rate: .* but iterations=|warning", re.IGNORECASE)
"""What a line of the docs must not say of itself: a learning-rate horizon that does not fit its run, a warning."""


DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def block(heading: str, page: str = "README.md") -> list[str]:
    """The command lines of the first code block after ``heading`` in ``page`` (comments and blank lines left out)."""
    section = ("\n" + (REPO / page).read_text()).split(f"\n{heading}\n", 1)[1]
    lines = section.split("```bash\n", 1)[1].split("\n```", 1)[0]
    return [line for line in lines.splitlines() if line.strip() and not line.startswith("#")]


def every_command() -> list[tuple[str, str]]:
    """(page, command) for every command of every bash block of the README and docs/, continuation lines joined and
    ``&&`` chains split."""
    found = []
    for page in DOCS:
        for code in page.read_text().split("```bash\n")[1:]:
            text = code.split("\n```", 1)[0].replace("\\\n", " ")
            for line in text.splitlines():
                line = line.split(" # ", 1)[0].strip()  # a comment after the command
                if line and not line.startswith("#"):
                    found += [(page.name, part.strip()) for part in line.split("&&")]
    return found


def using_it() -> list[str]:
    return block("## Using it")


def as_tested(line: str) -> str:
    words = shlex.split(line)
    command = words[words.index("ftrain") + 1] if "ftrain" in words else None
    if command in ("train", "supervise"):
        return f"{line} {shlex.join(SMOKE_SIZED)}"
    if command == "bench" or (words[0] == "python" and Path(words[1]).name.startswith("bench_")):
        return f"{line} --help"
    return line


def test_every_ftrain_command_of_the_docs_parses_its_config_loads_and_its_scripts_exist() -> None:
    from ftrain.cli import parse
    from ftrain.config import load_config

    checked = 0
    for page, command in every_command():
        words = shlex.split(command)
        while words and "=" in words[0] and not words[0].startswith("-"):  # FTRAIN_NNODES=1:2 sbatch ...
            words = words[1:]
        for word in words:
            if word.startswith(("launch/", "configs/", "examples/")):
                assert (REPO / word).exists(), f"{page}: {command!r} names {word}, which does not exist"
        if words[0] == "sbatch":  # the script's arguments are ftrain supervise's
            words = ["ftrain", "supervise", *words[words.index("launch/slurm.sbatch") + 1 :]]
        if words[0] != "ftrain" and "ftrain" not in words[:6]:
            continue
        arguments = words[words.index("ftrain") + 1 :]
        try:
            args = parse(arguments)
        except SystemExit:
            pytest.fail(f"{page}: {command!r} does not parse")
        if args.command in ("train", "supervise"):
            load_config(args.config, args.overrides, args.storage)  # a UserError names the key
        checked += 1
    assert checked >= 20, f"only {checked} ftrain commands found in the docs"


def anchors(page: Path) -> set[str]:
    """The anchors GitHub makes of a page's headings: lower case, punctuation dropped, spaces as hyphens."""
    headings = re.findall(r"^#+ (.+)$", re.sub(r"```.*?```", "", page.read_text(), flags=re.S), flags=re.M)
    return {re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-") for heading in headings}


def test_every_link_of_the_readme_and_the_docs_leads_somewhere() -> None:
    relative = re.compile(r"\]\(([^)#:\s]*)(?:#([^)\s]*))?\)")  # a link or image, not a URL; its anchor if any
    links = [(page, target, anchor) for page in DOCS for target, anchor in relative.findall(page.read_text())]
    missing = [f"{page.name} -> {target}" for page, target, _ in links if not (page.parent / target).exists()]
    assert not missing and len(links) >= 10, missing  # pages, images and files, relative to the page
    sections = [  # a heading of a page of the docs: a file of another kind has no anchors of that form
        (page.parent / target if target else page, anchor)
        for page, target, anchor in links
        if anchor and (not target or target.endswith(".md"))
    ]
    astray = [f"{page.name}#{anchor}" for page, anchor in sections if anchor not in anchors(page.resolve())]
    assert not astray and len(sections) >= 10, f"links to no heading of their page: {astray}"
    print(f"{len(links)} links, {len(sections)} of them to a heading, all found")
    pages = {target.split("/")[-1] for page, target, _ in links if page.name == "README.md" and target.endswith(".md")}
    assert pages == {page.name for page in DOCS[1:]}, "the README links every page of docs/"


def test_every_config_key_is_in_the_docs() -> None:
    """Every key of the config (generated from its dataclasses, so that a new key is covered): named in backticks in
    docs/, itself (`algorithm.gamma`, `algorithm.schedule=linear`) or as a key of its section's row (`algorithm.*`:
    `gamma`); `ftrain train --help` listed some that the docs did not."""
    from ftrain.config import Config
    from ftrain.values import dotted

    docs = "".join(path.read_text() for path in sorted((REPO / "docs").glob("*.md")))
    rows = {line.split("`")[1][:-2]: line for line in docs.splitlines() if re.match(r"\| `[a-z_.]+\.\*` \|", line)}
    keys = dotted(Config().to_dict())
    missing = []
    for key in keys:
        section, _, leaf = key.rpartition(".")
        named = re.search(rf"`{re.escape(key)}[`= ]", docs)
        if not named and f"`{leaf}`" not in rows.get(section, "") and f"`{section}.*`" not in docs:
            missing.append(key)
    print(f"{len(keys)} config keys, each in docs/")
    assert not missing, missing


@pytest.mark.slow
def test_the_main_job_trains_where_storage_says(tmp_path) -> None:
    """``launch/run.sh --storage X`` trains in X, not in its default runs/halfcheetah (its header's example). It runs
    the set-up first, so only where this checkout's .venv is set up (as ``launch/test.sh`` leaves it)."""
    if not list((REPO / ".venv").glob(".ftrain-setup-*")):
        pytest.skip("this checkout has no .venv set up by launch/setup.sh")
    storage = tmp_path / "hc"
    overrides = ["iterations=2", "checkpoint.interval=1", *SMOKE_SIZED]
    command = ["bash", "launch/run.sh", "--storage", str(storage), f"log_dir={tmp_path / 'logs'}", *overrides]
    result = subprocess.run(command, cwd=REPO, env=child_env(), capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-2000:] + result.stderr[-3000:]
    assert (storage / "checkpoints/step-000000002/MANIFEST.json").exists(), result.stdout[-2000:]


@pytest.mark.slow
def test_every_line_of_using_it_works_as_written(tmp_path) -> None:
    lines = using_it()
    assert any(line.startswith("ftrain ckpt show") for line in lines), "no README block found"
    run_as_a_reader(tmp_path, lines)


@pytest.mark.slow
def test_every_line_of_your_own_robot_works_as_written(tmp_path) -> None:
    """docs/own-robot.md's walk-through: train the example arm, show its identity, play it on video, export it."""
    lines = block("# Your own robot", "docs/own-robot.md")
    assert any("configs/reach.yaml" in line for line in lines), "no README block found"
    run_as_a_reader(tmp_path, lines)


def run_as_a_reader(tmp_path: Path, lines: list[str]) -> None:
    """Run ``lines`` in order in a scratch directory laid out like the repository, each in a shell that ran the
    block's ``source`` lines above it first."""
    if sys.prefix == sys.base_prefix:
        pytest.skip("the block activates a virtualenv: run the tests with one (.venv/bin/python -m pytest)")
    (tmp_path / ".venv").symlink_to(sys.prefix)
    for name in ("configs", "launch", "examples"):
        (tmp_path / name).symlink_to(REPO / name)
    setup: list[str] = []
    for line in lines:
        if line.startswith("source "):
            setup.append(line)  # as in a reader's shell, it holds for every line below it
            continue
        result = subprocess.run(
            ["bash", "-c", " && ".join([*setup, as_tested(line)])],
            cwd=tmp_path,
            env=child_env({"PYTHONPATH": str(REPO)}),
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert result.returncode == 0, f"README line {line!r}: exit {result.returncode}\n{result.stderr[-3000:]}"
        said = result.stdout + result.stderr
        assert not SELF_WARNINGS.search(said), f"README line {line!r} warns about its own settings:\n{said[-3000:]}"
        words = shlex.split(line)
        for option, value in itertools.pairwise(words):
            if option in OUTPUT_OPTIONS:
                assert (tmp_path / value).stat().st_size > 0, f"README line {line!r} did not write {value}"
    assert setup, "the block no longer activates the virtualenv: the lines above ran without it"
