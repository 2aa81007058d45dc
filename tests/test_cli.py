"""The command line's own surface: help for every option and its default, ``--version``, choices refused early."""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import re
import signal
import subprocess
import sys

import pytest

from ftrain.ckpt.storage import Storage
from ftrain.cli import build_parser, main, parsers

from helpers import REPO, SMOKE, child_env, make_step, train_command


def ftrain(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ftrain", *args], cwd=REPO, capture_output=True, text=True, timeout=60)


def test_every_option_command_and_argument_has_help() -> None:
    missing = []
    for name, parser in parsers(build_parser()):
        for action in parser._actions:
            listed = action._choices_actions if isinstance(action, argparse._SubParsersAction) else []
            for each in [action, *listed]:
                if not isinstance(each, argparse._HelpAction) and not (each.help or "").strip():
                    missing.append(f"{name} {each.option_strings[-1] if each.option_strings else each.dest}")
    assert not missing, f"no help text: {missing}"


def test_every_commands_help_opens_with_what_it_does() -> None:
    described = {name: (parser.description or "").strip() for name, parser in parsers(build_parser())}
    assert all(described.values()), [name for name, text in described.items() if not text]
    assert described["ftrain plot"] == "Learning curves of a run as a PNG, restarts marked."
    print(f"{len(described)} commands described")


def test_every_option_with_a_default_shows_it() -> None:
    hidden = []
    for name, parser in parsers(build_parser()):
        for action in parser._actions:
            shown = action.default in (None, False, [], "", argparse.SUPPRESS) or "%(default)" in (action.help or "")
            if action.option_strings and not shown:
                hidden.append(f"{name} {action.option_strings[-1]}")
    assert not hidden, f"a default --help does not show: {hidden}"
    supervise = ftrain("supervise", "--help").stdout
    assert "(default: 10)" in supervise and "(default: auto)" in supervise


def test_supervise_help_lists_the_exit_codes_and_what_a_stop_signal_does() -> None:
    from ftrain.supervise.options import EXIT_CODES

    text = ftrain("supervise", "--help").stdout
    assert "SIGTERM, SIGHUP (a closed terminal) or SIGINT (Ctrl-C) to the supervisor makes the workers save" in text
    for code, meaning in EXIT_CODES.items():
        assert f"{code:>5}  {meaning}" in text
    docs = (REPO / "docs" / "supervision.md").read_text()
    assert all(f"\n| {code} |" in docs for code in EXIT_CODES), "the docs' exit-code table lists every code"


def test_version_is_the_installed_one() -> None:
    result = ftrain("--version")
    assert result.returncode == 0
    assert result.stdout == f"ftrain {importlib.metadata.version('ftrain')}\n"


def test_export_format_is_one_of_the_choices() -> None:
    result = ftrain("export", "no-such-run", "--format", "tflite")
    assert result.returncode == 2
    assert "argument --format: invalid choice: 'tflite' (choose from 'torchscript', 'onnx')" in result.stderr
    assert "Traceback" not in result.stderr


def test_help_lists_every_subcommand() -> None:
    result = ftrain("--help")
    assert result.returncode == 0
    for command in ("train", "supervise", "ckpt", "bench", "play", "export", "plot"):
        assert command in result.stdout


def test_train_help_lists_every_config_key_with_its_default() -> None:
    result = ftrain("train", "--help")
    assert result.returncode == 0
    for line in ("--storage", "env.num_envs=16", "checkpoint.keep_last=3", "algorithm.clip_param=0.2", "resume='auto'"):
        assert line in result.stdout


def test_torchruns_underscore_spellings_are_taken_and_a_split_list_override_says_to_quote_it() -> None:
    from ftrain.cli import parse

    args = parse(["supervise", "--nproc_per_node", "2", "--max_restarts", "5", "configs/smoke.yaml"])
    assert (args.nproc_per_node, args.max_restarts) == (2, 5)
    assert parse(["supervise", "configs/smoke.yaml"]).nproc_per_node is None  # not given: from the storage
    assert "--nproc_per_node" not in ftrain("supervise", "--help").stdout
    split = ftrain("train", "configs/smoke.yaml", "policy.hidden_dims=[64,", "64]")
    assert split.returncode == 2 and "Traceback" not in split.stderr
    said = "override policy.hidden_dims=[64, 64] has a space: quote it as one word, 'policy.hidden_dims=[64, 64]'"
    assert split.stderr == f"ftrain: error: {said}\n", split.stderr


def test_a_usage_error_is_one_line_naming_the_commands_help_and_a_bare_word_is_told_as_an_override(tmp_path) -> None:
    cases = [  # (arguments, the error line)
        (["train"], "ftrain: error: the following arguments are required: config: see ftrain train --help"),
        (["ckpt"], "required: ACTION (one of: ls, verify, show, prune, unquarantine): see ftrain ckpt --help"),
        (["train", "configs/smoke.yaml", "--bogus"], "unrecognized arguments: --bogus: see ftrain train --help"),
        (["ckpt", "ls", str(tmp_path), "--stroage-option", "a=b"], "(did you mean --storage-option?): see ftrain ckpt"),
        (["trian", "configs/smoke.yaml"], "invalid choice: 'trian' (choose from "),
        (["train", "configs/smoke.yaml", "-q", "-v"], "argument -v/--verbose: not allowed with argument -q/--quiet: "),
        (
            ["supervise", "configs/smoke.yaml", "--storage", str(tmp_path / "run"), "iterations"],
            "ftrain: error: override 'iterations' is not key=value: write it like env.num_envs=8",
        ),
        (
            ["train", str(tmp_path)],
            f"ftrain: error: config file '{tmp_path}' is a directory: pass the path of a YAML file such as ",
        ),
    ]
    for args, error in cases:
        result = ftrain(*args)
        assert result.returncode == 2 and result.stderr.count("\n") == 1 and error in result.stderr, (args, result)
    assert "(did you mean train?)" in ftrain("trian").stderr
    assert not (tmp_path / "run").exists()
    print(f"{len(cases) + 1} usage errors checked")


def test_a_misspelt_option_or_choice_is_told_the_one_it_is_closest_to() -> None:
    """Generated cases: every listed long option and every choice of every command, each with one of its letters
    dropped (never the last: a prefix is argparse's abbreviation), is refused with the option or choice it came from."""
    from ftrain.cli import parse
    from ftrain.errors import UserError

    checked = 0
    for name, parser in parsers(build_parser()):
        command, needed, words = name.split()[1:], [], []  # needed: what comes before an unknown option is told
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):  # a command misspelt, where the parser takes one
                words += [([choice], choice) for choice in action.choices]
            elif not action.option_strings and action.nargs != "*":
                needed.append("x")
            elif action.required:
                needed += [action.option_strings[-1], next(iter(action.choices))]
        if not words:  # a command that runs: its options and their choices misspelt
            listed = [action for action in parser._actions if action.help != argparse.SUPPRESS]
            words += [([*needed, o], o) for a in listed for o in a.option_strings if o.startswith("--")]
            words += [([*needed, a.option_strings[-1], c], c) for a in listed if a.choices for c in a.choices]
        known = [word[-1] for word, _ in words]
        for word, meant in words:
            bare = meant.lstrip("-")
            dropped = [meant[:index] + meant[index + 1 :] for index in range(len(meant) - len(bare), len(meant) - 1)]
            start = [] if meant.startswith("-") else [meant[:3]]  # argparse takes a start of an option, not of a word
            for typo in [*dropped, meant.upper(), *start]:
                shared = [other for other in known if other.lower().startswith(typo.lower())]
                taken = typo.startswith("-") and any(other.startswith(typo) for other in known)
                if len(bare) < 4 or taken or (typo in start and shared != [meant]):
                    continue  # too short to tell from another, an abbreviation argparse takes, a start of two
                argv = [*command, *word[:-1], typo]
                try:
                    parse(argv)
                except UserError as error:
                    line = str(error)
                    assert f"(did you mean {meant}?)" in line and f"see {name} --help" in line, (argv, line)
                    checked += 1
                else:
                    raise AssertionError(f"{argv} was taken")
    opposites = [["ckpt", "prune", "x", f"--{no}drop{joint}bad"] for no in ("no", "no-", "no_") for joint in "-_"]
    opposites += [["ckpt", "prune", "x", "--nodropbad"], ["ckpt", "prune", "x", "--no-force"], ["ckpt", "quarantin"]]
    for argv in [*opposites, ["ckpt", "quarantine"], ["pl"], ["ckpt", "prune", "x", "--keep"]]:
        with pytest.raises(UserError) as refused:  # the opposite of what was typed, or one of several, is no suggestion
            parse(argv)
        assert "did you mean" not in str(refused.value), argv
    print(f"{checked} misspelt options and choices told the one they came from")
    assert checked > 400


def test_an_option_before_the_command_is_told_where_it_goes() -> None:
    """Generated cases: every listed option of every command (flags, ``--opt X``, ``--opt=X``) given before the
    command, or between its words (``ftrain --json ckpt show``, ``ftrain ckpt --json show``), is told to go after the
    command, where argparse said the command was not one, or a missing one, or suggested the option typed; an option
    ``ftrain`` does not have, alone, is told the one it is closest to."""
    from ftrain.cli import parse
    from ftrain.errors import UserError

    checked = 0
    for name, parser in parsers(build_parser()):
        path = name.split()[1:]
        if not path or any(isinstance(a, argparse._SubParsersAction) for a in parser._actions):
            continue  # ftrain itself, or a command with commands under it
        listed = [a for a in parser._actions if a.help != argparse.SUPPRESS and a.option_strings]
        for action in (a for a in listed if "--help" not in a.option_strings):
            for option in action.option_strings:
                forms = [[option]] if action.nargs == 0 else [[option, "x"], [f"{option}=x"]]
                for form in forms:
                    for place in range(len(path)):
                        argv = [*path[:place], *form, *path[place:], "x"]
                        with pytest.raises(UserError) as refused:
                            parse(argv)
                        told = f"{option} goes after the command: {name} ... {option} ...: see {name} --help"
                        assert str(refused.value) == told, (argv, str(refused.value))
                        checked += 1
    for argv, line in [
        (["--verison"], "unrecognized arguments: --verison (did you mean --version?): see ftrain --help"),
        (["--bogus"], "unrecognized arguments: --bogus: see ftrain --help"),
        (["-"], "unrecognized arguments: -: see ftrain --help"),  # argparse's own look-up failed on it: a traceback
        (["ckpt", "-", "ls", "x"], "argument ACTION: invalid choice: '-' (choose from 'ls', 'verify', 'show', "),
        (["ckpt", "--json"], "the following arguments are required: ACTION (one of: ls, verify, show, prune, "),
        (["--json", "x"], "--json goes after a command: ftrain COMMAND ... --json ... (it is an option of ckpt): "),
    ]:
        with pytest.raises(UserError, match=f"^{re.escape(line)}"):
            parse(argv)
        checked += 1
    print(f"{checked} options before the command told where they go")
    assert checked > 100


def test_a_start_of_an_option_spelt_two_ways_is_that_option() -> None:
    """argparse takes a start of an option; ``--nproc`` starts both spellings of --nproc-per-node, which is no
    ambiguity (it was refused as one)."""
    from ftrain.cli import parse

    assert parse(["supervise", "configs/smoke.yaml", "--nproc", "3"]).nproc_per_node == 3


def test_a_path_the_terminal_cannot_encode_is_escaped_not_a_crash(tmp_path) -> None:
    """On an ASCII stdout a storage named in ü was a UnicodeEncodeError after training, in every attempt of a
    supervised run (a crash loop), and in ``ckpt show``."""
    storage = tmp_path / "ü run"
    env = child_env({"PYTHONIOENCODING": "ascii"})
    trained = subprocess.run(train_command(storage, "iterations=2"), env=env, capture_output=True, text=True)
    assert trained.returncode == 0, trained.stderr[-2000:]
    shown = subprocess.run(
        [sys.executable, "-m", "ftrain", "ckpt", "show", str(storage)], env=env, capture_output=True, text=True
    )
    assert shown.returncode == 0 and "\\xfc run" in shown.stdout, shown.stderr[-2000:]


def test_a_path_that_is_not_utf8_is_one_line_and_nothing_made(tmp_path) -> None:
    """Bytes that are not UTF-8 in a path (Latin-1's \\xff) were a traceback when the log directory was claimed, with
    the lease and lock files left in a new storage; in a config's name, a traceback naming the process."""
    storage = os.fsencode(tmp_path) + b"/bad\xff"
    for command in ([b"train", SMOKE.encode(), b"--storage", storage], [b"supervise", b"bad\xff.yaml"]):
        done = subprocess.run(
            [sys.executable.encode(), b"-m", b"ftrain", *command], capture_output=True, env=child_env()
        )
        said = done.stderr.decode()
        assert done.returncode == 2 and len(said.splitlines()) == 1, said
        assert re.search(r"bad\\xff(\.yaml)?' is not UTF-8: ftrain reads paths and values as UTF-8: rename it", said), (
            said
        )
    assert list(tmp_path.iterdir()) == []


KEEP_LINE_BESIDE = [
    ["--keep-last", "1"],
    ["--keep-best", "2"],
    ["--best-metric", "eval_return"],
    ["--keep-every", "5"],
    ["--pin", "4"],
    ["--drop-bad"],
    ["--keep-last", "1", "--pin", "2", "--drop-bad"],
]


@pytest.mark.parametrize("rules", KEEP_LINE_BESIDE)
def test_keep_line_beside_retention_rules_is_refused_in_one_line(tmp_path, capsys, rules: list[str]) -> None:
    """``prune --keep-line S`` replaces the retention rules: given beside it they did nothing, without a word."""

    make_step(Storage.open(str(tmp_path / "run")), 4)
    before = sorted(path.relative_to(tmp_path) for path in tmp_path.rglob("*"))
    assert main(["ckpt", "prune", str(tmp_path / "run"), "--keep-line", "4", *rules]) == 2
    err = capsys.readouterr().err
    named = [word for word in rules if word.startswith("--")]
    assert err.count("\n") == 1 and "would do nothing beside it: run the two as two commands" in err, err
    assert f"instead of the retention rules: {', '.join(named)} would" in err, err
    assert sorted(path.relative_to(tmp_path) for path in tmp_path.rglob("*")) == before
    assert main(["ckpt", "prune", str(tmp_path / "run"), "--keep-line", "4", "--dry-run"]) == 0
    assert "would keep the line of step 4: 1 step; 0 would set aside" in capsys.readouterr().out


@pytest.mark.parametrize("command", ["train", "supervise"])
def test_storage_given_twice_is_refused_unless_it_is_the_same_one(tmp_path, capsys, command: str) -> None:
    """argparse takes the last of a repeated option: a run would go to one storage while the user meant the other, as
    ``--storage A storage.url=B`` (refused in the config). Its credentials stay out of the line."""
    first, second = str(tmp_path / "a"), "s3://KEY:SECRET@bucket/run"
    assert main([command, "configs/halfcheetah.yaml", "--storage", first, "--storage", second]) == 2
    err = capsys.readouterr().err
    assert (
        err == f"ftrain: error: --storage {first} and --storage s3://bucket/run name two storages: pass one of them\n"
    )
    assert main([command, "configs/halfcheetah.yaml", "--storage", "", "--storage", first]) == 2
    assert (
        capsys.readouterr().err
        == f"ftrain: error: --storage '' and --storage {first} name two storages: pass one of them\n"
    )
    again = [command, "x.yaml", "--storage", first, "--storage", f"file://{first}/"]  # one storage, spelt two ways
    assert build_parser().parse_args(again).storage == f"file://{first}/"


def test_storage_options_for_a_local_path_are_refused_by_every_command_that_takes_them(tmp_path, capsys) -> None:
    """fsspec opens a local path without a word about options it does nothing with: a remote URL written without its
    protocol, most likely. Every command with ``--storage-option`` (found in the parser, so that a new one is
    covered) refuses it in one line, and makes nothing; options beside a remote ``resume=`` or teacher are used."""
    from ftrain.config import check_options_used

    local = tmp_path / "bucket" / "run"
    checked = []
    for name, parser in parsers(build_parser()):
        if not any("--storage-option" in action.option_strings for action in parser._actions):
            continue
        words = name.split()[1:]
        place = [SMOKE, "--storage", str(local)] if words[-1] in ("train", "supervise") else [str(local)]
        place += ["--format", "onnx"] if words[-1] == "export" else []
        args = [*words, *place, "--storage-option", "endpoint_url=http://127.0.0.1:9", "--storage-option", "key=K"]
        assert main(args) == 2, args
        err = capsys.readouterr().err
        expected = f"--storage-option endpoint_url, key: {local} is a local path, where storage options do nothing: "
        assert err.count("\n") == 1 and expected in err and "leave --storage-option out" in err, (args, err)
        checked.append(name)
    assert {"ftrain train", "ftrain supervise", "ftrain ckpt prune", "ftrain play", "ftrain plot"} <= set(checked)
    assert not (tmp_path / "bucket").exists()
    print(f"{len(checked)} commands refuse storage options for a local path: {', '.join(checked)}")
    for remote in ("s3://bucket/run", "gs://bucket/step-000000004"):  # a resume= or teacher= on a remote storage
        check_options_used(["endpoint_url=http://127.0.0.1:9"], [str(local), remote, ""])
    check_options_used([], [str(local)])


def test_a_name_longer_than_its_file_system_takes_is_one_line_and_nothing_made(tmp_path, capsys) -> None:
    """A path with a name of 300 bytes was a traceback (``export -o``, ``play --video``, ``plot -o``, a config, a log
    directory) or a line with exit 1 and no fix (a storage, ``resume=``)."""
    long = str(tmp_path / ("x" * 300))
    run = str(tmp_path / "run")
    cases = [
        ["train", f"{long}.yaml"],
        ["train", SMOKE, "--storage", long],
        ["train", SMOKE, "--storage", run, f"resume={long}"],
        ["ckpt", "ls", long],
        ["plot", run, "-o", f"{long}.png"],
        ["export", run, "--format", "onnx", "-o", f"{long}.onnx"],
        ["play", run, "--video", f"{long}.mp4"],
    ]
    for args in cases:
        assert main(args) == 2, args
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "that path, or a name in it, is longer than its file system takes" in err, (
            args,
            err,
        )
    assert list(tmp_path.iterdir()) == []
    print(f"{len(cases)} commands refuse a name of 300 bytes in one line")


def test_a_lost_stop_is_raised_once_and_a_stop_said_is_not_lost(monkeypatch, capsys) -> None:
    """``raise_lost_stop`` raises a stop whose exception was lost (a library's ``except BaseException``) where a command
    takes its signals over or ends, once; a stop that was handled and said (``stopped``) is none."""
    from ftrain import errors

    monkeypatch.setattr(errors, "_received", [])
    monkeypatch.setattr(errors, "_said", [])
    with pytest.raises(errors.Terminated):
        errors.raise_stop(signal.SIGTERM, None)  # its exception swallowed on the way
    with pytest.raises(errors.Terminated):
        errors.raise_lost_stop()
    errors.raise_lost_stop()  # raised once
    with pytest.raises(KeyboardInterrupt):
        errors.raise_stop(signal.SIGINT, None)
    assert errors.stopped(signal.SIGINT) == 130
    errors.raise_lost_stop()  # said: not lost
    assert capsys.readouterr().err == "ftrain: interrupted (Ctrl-C)\n"
