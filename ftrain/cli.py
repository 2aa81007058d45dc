"""Command line: argument parsing only. Each subcommand is a thin call into a module below.

Heavy modules (torch, rsl_rl, gymnasium) are imported inside the subcommand that needs them, so
``ftrain --help`` and ``ftrain supervise`` start fast.
"""

from __future__ import annotations

import argparse
import codecs
import contextlib
import dataclasses
import errno
import importlib.metadata
import io
import os
import re
import select
import signal
import sys
import typing
from pathlib import Path

from ftrain import errorfile
from ftrain.errors import (
    CONTINUE,
    EXIT_FAILED,
    EXIT_STORAGE_DOWN,
    EXIT_USAGE,
    NO_SPACE,
    STOPPED,
    StorageError,
    StorageUnavailable,
    Terminated,
    UserError,
    name_too_long_line,
    no_space_line,
    stop_on_signals,
    stop_signal,
    stopped,
)
from ftrain.lifeline import SUPERVISOR_ENV, watch_launcher
from ftrain.process import imports
from ftrain.proctitle import name_process, rank_role
from ftrain.redact import display_url, reveal_credentials
from ftrain.terminal import outlive_a_hangup

if typing.TYPE_CHECKING:
    from ftrain.config import Config

EXIT_BROKEN_PIPE = 128 + signal.SIGPIPE
"""The reader of stdout went away (``ftrain ... | head``): what a shell reports for a tool killed by SIGPIPE."""
OVERRIDES_HELP = (
    "config overrides as dotted key=value, values parsed as YAML (e.g. env.num_envs=8 policy.hidden_dims=[64,64]); "
    "of a key given twice, the later wins"
)


QUIET, VERBOSE = "log.console=false", "log.console_saves=every"
"""What ``-q`` and ``-v`` stand for: overrides, which reach every worker with the others."""


class _Parser(argparse.ArgumentParser):
    """A usage error is one line, a UserError like every bad input (the error file of a worker says it too): what is
    wrong, the option or command closest to a misspelt one, and the command's ``--help``; not argparse's usage block."""

    def error(self, message: str) -> typing.NoReturn:
        raise UserError(f"{message}{_closest(self, message)}: see {self.prog} --help")

    def _get_option_tuples(self, option_string: str) -> list:
        """argparse's options that ``option_string`` abbreviates, one per option: ``--nproc`` abbreviates the two
        spellings of --nproc-per-node, which is no ambiguity."""
        tuples, seen = [], set()
        for found in super()._get_option_tuples(option_string):
            if found[0].dest not in seen:
                seen.add(found[0].dest)
                tuples.append(found)
        return tuples


def _closest(parser: argparse.ArgumentParser, message: str) -> str:
    """`` (did you mean --storage?)`` for the first unrecognized option or invalid choice in argparse's ``message``,
    where one of ``parser``'s is close; `` (one of: ...)`` for a missing command."""
    from ftrain.errors import closest

    commands = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
    if commands is not None and message.endswith(f"required: {commands.metavar}"):
        return f" (one of: {', '.join(commands.choices)})"
    if (choice := re.search(r"argument (\S+): invalid choice: '([^']*)'", message)) is not None:
        names = {"/".join(a.option_strings) or a.metavar or a.dest: a for a in parser._actions}  # as argparse names it
        known, word = list(getattr(names.get(choice[1]), "choices", None) or []), choice[2]
    elif (option := re.search(r"unrecognized arguments: (--?[^\s=]+)", message)) is not None:
        listed = [a for a in parser._actions if a.help != argparse.SUPPRESS]  # not the underscore spellings
        known, word = [o for a in listed for o in a.option_strings if o.startswith("--")], option[1]
    else:
        return ""
    bare = {name.lstrip("-"): name for name in known}  # the dashes every option shares are no likeness
    near = closest(word.lstrip("-"), bare)
    return f" (did you mean {bare[near]}?)" if near else ""


class _OneStorage(argparse.Action):
    """``--storage`` given twice for two storages is refused, as ``--storage A storage.url=B`` is: taking the last
    would train into, or resume from, a storage the user may not have meant."""

    def __call__(
        self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, value: str, option: str | None = None
    ) -> None:
        from ftrain.config import same_storage

        if (before := getattr(namespace, self.dest, None)) is not None and not same_storage(before, value):
            shown = " and ".join(f"--storage {display_url(url) or repr('')}" for url in (before, value))
            raise UserError(f"{shown} name two storages: pass one of them")
        setattr(namespace, self.dest, value)


def _add_run_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("config", help="YAML config file, e.g. configs/halfcheetah.yaml")
    parser.add_argument(
        "--storage",
        action=_OneStorage,
        help="where checkpoints go: a local path (default runs/<name>), file://, s3://...",
    )
    _add_storage_options(parser)
    loudness = parser.add_mutually_exclusive_group()
    loudness.add_argument(
        "-q", "--quiet", dest="loudness", action="store_const", const=QUIET, help="no line per iteration or save"
    )
    loudness.add_argument(
        "-v", "--verbose", dest="loudness", action="store_const", const=VERBOSE, help="a line for every save"
    )
    parser.add_argument("overrides", nargs="*", default=(), metavar="key=value", help=OVERRIDES_HELP)  # optional


def _add_storage_options(parser: argparse.ArgumentParser) -> None:
    """``--storage-option``, the same on every command that opens a storage (``values.storage_option_overrides``)."""
    from ftrain.values import STORAGE_OPTION

    parser.add_argument(
        STORAGE_OPTION,
        dest="storage_option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an fsspec storage option, value parsed as YAML (repeatable; the same as storage.options.KEY=VALUE), "
        "e.g. endpoint_url=http://127.0.0.1:9000 key=... secret=...; S3 also reads the AWS_* environment",
    )


def _add_dataclass_arguments(parser: argparse.ArgumentParser, options_class: type) -> None:
    """One ``--flag`` per dataclass field, typed by its default, documented by its ``help`` metadata and default (or,
    with ``unset`` metadata, None where not given, and ``unset`` says what that means); its underscore spelling
    (``--nproc_per_node``, which torchrun takes too) is taken, unlisted."""
    hints = typing.get_type_hints(options_class)
    for field in dataclasses.fields(options_class):
        flag = "--" + field.name.replace("_", "-")
        kind = next((arg for arg in typing.get_args(hints[field.name]) if arg is not type(None)), hints[field.name])
        kind = kind if kind in (int, float) else str  # ``float | None``: a float, None where the help says why
        default = None if "unset" in field.metadata else field.default
        shown = field.metadata.get("unset", "%(default)s" if field.default not in ("", None) else None)
        help_text = field.metadata["help"] + (f" (default: {shown})" if shown else "")
        parser.add_argument(flag, dest=field.name, type=kind, default=default, help=help_text)
        if "_" in field.name:
            hidden = {"type": kind, "default": argparse.SUPPRESS, "help": argparse.SUPPRESS}
            parser.add_argument("--" + field.name, dest=field.name, **hidden)


def _config_keys_help() -> str:
    """Every config key with its default, for ``ftrain train --help`` (docs/configuration.md explains them)."""
    from ftrain.config import Config

    def flatten(data: dict, prefix: str = "") -> list[str]:
        lines = []
        for key, value in data.items():
            if isinstance(value, dict) and value and key not in ("kwargs", "options"):
                lines += flatten(value, f"{prefix}{key}.")
            else:
                lines.append(f"  {prefix}{key}={value!r}")
        return lines

    return "config keys and their defaults (override any as key=value):\n" + "\n".join(flatten(Config().to_dict()))


def build_parser() -> argparse.ArgumentParser:
    from ftrain.config import POLICY_FORMATS
    from ftrain.supervise.options import SupervisorOptions, exit_codes_help

    parser = _Parser(
        prog="ftrain", description="Distributed, fault-tolerant PPO training on CPU (torchrun + gloo + rsl-rl)."
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", help="one of:")

    train = commands.add_parser(
        "train",
        help="train (run under torchrun for several processes)",
        description="Train PPO. Under torchrun every rank runs this; alone it runs one process (world size 1).",
        epilog=_config_keys_help(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_run_arguments(train)

    supervise = commands.add_parser(
        "supervise",
        help="launch torchrun and restart it from the newest verified checkpoint after a crash or hang",
        description="Watchdog: launches torchrun, detects crashes, hangs and preemption, restarts from the newest "
        "verified checkpoint.",
        epilog=exit_codes_help(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_dataclass_arguments(supervise, SupervisorOptions)
    _add_run_arguments(supervise)

    storage_url = "a run's storage (local path, file:// or s3://)"
    step_url = "one checkpoint step <root>/checkpoints/step-N"
    newest = f"{storage_url} for its newest verified step"
    ckpt = commands.add_parser("ckpt", help="inspect and repair checkpoint storage")
    ckpt_commands = ckpt.add_subparsers(dest="ckpt_command", required=True, metavar="ACTION", help="one of:")
    ls = ckpt_commands.add_parser("ls", help="list steps: committed (by sizes) / incomplete / corrupt / quarantined")
    ls.add_argument("url", help=f"{storage_url}, or {step_url}")
    _add_storage_options(ls)
    verify = ckpt_commands.add_parser(
        "verify", help="verify every file of a storage (policy snapshots too) or of one step (exit 1 on failure)"
    )
    verify.add_argument("url", help=f"{storage_url}, {step_url}, or one policy snapshot <root>/policies/step-N")
    _add_storage_options(verify)
    show = ckpt_commands.add_parser("show", help="print the manifest of one step (default: newest verified)")
    show.add_argument("url", help=f"{step_url}, or {newest}")
    show.add_argument("--json", action="store_true", help="raw JSON")
    _add_storage_options(show)
    prune = ckpt_commands.add_parser("prune", help="apply a retention policy")
    prune.add_argument("url", help=storage_url)
    _add_storage_options(prune)
    own = "default: the run's own checkpoint.{}, as ftrain ckpt ls marks it"
    prune.add_argument(
        "--keep-last", type=int, metavar="N", help=f"keep the newest N verified steps ({own.format('keep_last')})"
    )
    prune.add_argument(
        "--keep-best", type=int, metavar="N", help=f"keep the N best steps by --best-metric ({own.format('keep_best')})"
    )
    prune.add_argument(
        "--best-metric",
        help=f"the metric that ranks steps for --keep-best, higher is better ({own.format('best_metric')})",
    )
    prune.add_argument(
        "--keep-every",
        type=int,
        metavar="N",
        help=f"also keep every multiple of N (0: off; {own.format('keep_every')})",
    )
    prune.add_argument(
        "--pin",
        type=int,
        action="append",
        default=[],
        metavar="STEP",
        help="a step to keep, besides the run's pinned ones (repeatable)",
    )
    prune.add_argument(
        "--dry-run",
        action="store_true",
        help="print what would be deleted, delete nothing (exit 8 where a live run holds the storage: as prune)",
    )
    prune.add_argument(
        "--drop-bad", action="store_true", help="also delete corrupt, quarantined and set-aside steps (the only way)"
    )
    prune.add_argument(
        "--keep-line",
        type=int,
        metavar="STEP",
        help="instead of the retention rules: keep the line of descent that ends at STEP (the newest step of a "
        "line) and set every verified step off it aside (a forked storage)",
    )
    prune.add_argument(
        "--force", action="store_true", help="prune even while a run holds the storage (it refuses by default)"
    )
    unquarantine = ckpt_commands.add_parser(
        "unquarantine",
        help="lift the quarantine of one step if it verifies, or put a step set aside back where it may go (exit 1 "
        "if it does not verify)",
    )
    unquarantine.add_argument("url", help=f"{step_url}, or one set aside <root>/quarantine/step-N")
    _add_storage_options(unquarantine)

    bench = commands.add_parser("bench", help="throughput benchmark against rsl-rl and stable-baselines3")
    bench.add_argument(
        "--iterations",
        type=int,
        default=30,
        help="timed iterations per case, after a few warm-up ones (default: %(default)s)",
    )
    bench.add_argument(
        "--settings",
        nargs="+",
        choices=["fixed", "config"],
        default=["fixed", "config"],
        help="the work per iteration: the fixed first setting, the shipped HalfCheetah config's (default: %(default)s)",
    )

    policy_url = f"{step_url}, a policy snapshot <root>/policies/step-N, or {newest}"
    play = commands.add_parser(
        "play",
        help="roll out a policy and print its episode returns; --video renders it headless",
        description="Roll out a policy in its environment and print the episode returns. It takes the mean action "
        "(as rsl-rl and IsaacLab play); --stochastic samples. --video renders it headless (MUJOCO_GL=egl).",
    )
    play.add_argument("url", help=f"{policy_url}; or a file written by ftrain export")
    _add_storage_options(play)
    play.add_argument("--episodes", type=int, default=1, metavar="N", help="episodes to play (default: %(default)s)")
    play.add_argument(
        "--stochastic",
        action="store_true",
        help="sample actions from the policy's distribution, as in training (not for an exported file: it has only "
        "its mean actions)",
    )
    play.add_argument("--video", help="write a video: out.mp4 or out.gif")
    play.add_argument(
        "--seed", type=int, default=0, help="episodes are seeded seed, seed+1, ... (default: %(default)s)"
    )

    export = commands.add_parser(
        "export",
        help="write a self-contained, verified policy file (TorchScript or ONNX)",
        description="Export a policy with its observation normalizer; the file runs without ftrain. It is verified "
        "by comparing its actions with the trained actor's on real observations.",
    )
    export.add_argument("url", help=policy_url)
    _add_storage_options(export)
    export.add_argument(
        "--format",
        choices=POLICY_FORMATS,
        help="the file format; needed only where -o names no file (a directory, or none): -o FILE.pt or FILE.onnx "
        "names it",
    )
    export.add_argument(
        "-o",
        "--output",
        help="file to write, whose suffix names the format (.pt: torchscript, .onnx: onnx), or a directory to write "
        "it into (default: "
        "<run>/exports/<run name>-step-<N>.pt or .onnx)",
    )

    plot = commands.add_parser("plot", help="learning curves of a run as a PNG, restarts marked")
    plot.add_argument("run", help="the run's log directory (holds metrics.csv): a local path or an fsspec URL")
    _add_storage_options(plot)
    plot.add_argument(
        "-o",
        "--output",
        help="picture to write (.png, .svg, .pdf, .jpg: any matplotlib writes; .png if none), or a directory (default: "
        "<run>/curves.png)",
    )
    _describe(parser)
    return parser


def _describe(parser: argparse.ArgumentParser) -> None:
    """Every (sub)command's ``--help`` opens with what it does: its line in its parent's list, where it has no
    description of its own."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for listed in action._choices_actions:
                command = action.choices[listed.dest]
                command.description = command.description or f"{listed.help[0].upper()}{listed.help[1:]}."
                _describe(command)


def _version() -> str:
    """The installed ftrain's version (a source tree run without installing has none)."""
    try:
        return importlib.metadata.version("ftrain")
    except importlib.metadata.PackageNotFoundError:
        return "(not installed: pip install -e .)"


def parse(argv: list[str]) -> argparse.Namespace:
    """``argv`` as ``ftrain`` reads it: overrides may come before or after options such as --storage, and
    ``--storage-option``, ``-q`` and ``-v`` become overrides. A usage error or a bad value is a UserError."""
    for word in argv:
        try:
            word.encode()
        except UnicodeEncodeError:  # bytes the file system's encoding could not read, kept as surrogates
            shown = word.encode(errors="surrogateescape").decode(errors="backslashreplace")
            raise UserError(f"'{shown}' is not UTF-8: ftrain reads paths and values as UTF-8: rename it") from None
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
    except UserError:
        _refuse_misplaced_option(parser, argv)
        raise
    unknown = [word for word in extra if word.startswith("-")]  # a bare word is an override, checked as one
    if unknown or (extra and not hasattr(args, "overrides")):
        _refuse_misplaced_option(parser, argv)
        _command_parser(parser, args).error(f"unrecognized arguments: {' '.join(unknown or extra)}")
    if hasattr(args, "overrides"):
        from ftrain.values import storage_option_overrides

        args.overrides = [
            *args.overrides,
            *extra,
            *storage_option_overrides(args.storage_option),
            *filter(None, [args.loudness]),
        ]
    return args


def parsers(
    parser: argparse.ArgumentParser, name: str = "ftrain"
) -> typing.Iterator[tuple[str, argparse.ArgumentParser]]:
    """``ftrain`` and every (sub)command's parser, with its command line."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command, subparser in action.choices.items():
                yield from parsers(subparser, f"{name} {command}")


def _refuse_misplaced_option(parser: argparse.ArgumentParser, argv: list[str]) -> None:
    """A better line than argparse's where an option comes before the command it belongs to (``ftrain --storage X
    train ...`` was an invalid command X, ``ftrain --json ckpt show`` 'did you mean --json?'): where it goes; where
    ``ftrain`` starts with an option no command has (``ftrain --verison``), the closest of its own."""
    level, path, misplaced = parser, [], ""
    for word in argv:
        commands = next((a for a in level._actions if isinstance(a, argparse._SubParsersAction)), None)
        if commands is None:
            break  # the command reached: its options may come in any order from here
        if word in commands.choices:
            level, path = commands.choices[word], [*path, word]
        elif word.startswith("-") and not misplaced and not _takes(level, option := word.partition("=")[0]):
            misplaced = option
    if not misplaced or (any(isinstance(a, argparse._SubParsersAction) for a in level._actions) and path):
        return  # nothing misplaced, or a command still to name (``ftrain ckpt --json``): argparse lists them
    if path and _takes(level, misplaced):
        where = " ".join(["ftrain", *path])
        raise UserError(f"{misplaced} goes after the command: {where} ... {misplaced} ...: see {where} --help")
    if not path:
        takers = [
            name.split()[1] for name, command in parsers(parser) if name != "ftrain" and _takes(command, misplaced)
        ]
        if takers:
            raise UserError(
                f"{misplaced} goes after a command: ftrain COMMAND ... {misplaced} ... (it is an option of "
                f"{', '.join(dict.fromkeys(takers))}): see ftrain COMMAND --help"
            )
        parser.error(f"unrecognized arguments: {misplaced}")


def _takes(parser: argparse.ArgumentParser, option: str) -> bool:
    """Whether ``parser`` has ``option``, or an option ``option`` starts (argparse's abbreviation)."""
    if len(option) < 2:
        return False  # ``-`` alone: a word (argparse's own look-up fails on it)
    return option in parser._option_string_actions or bool(parser._get_option_tuples(option))


def _command_parser(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.ArgumentParser:
    """The parser of the (sub)command ``args`` ran, whose usage line an error shows."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction) and getattr(args, action.dest, None) in action.choices:
            return _command_parser(action.choices[getattr(args, action.dest)], args)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    outlive_a_hangup()
    stop_on_signals()
    _escape_what_stdout_cannot_encode()
    if argv[:1] == ["train"]:  # a worker of ``ftrain supervise``: the credentials come from the environment
        argv = ["train", *reveal_credentials(argv[1:], os.environ)]
    try:
        return _dispatch(parse(argv))
    except UserError as error:
        errorfile.report(str(error))
        return EXIT_USAGE
    except StorageUnavailable as error:
        errorfile.report(str(error))
        return EXIT_STORAGE_DOWN
    except StorageError as error:
        errorfile.report(str(error))
        return EXIT_FAILED
    except (KeyboardInterrupt, Terminated) as stop:
        return stopped(stop_signal(stop))
    except BrokenPipeError:
        if not _stdout_reader_gone():
            raise
        # e.g. ``ftrain ckpt show URL | head -1``: stop like a tool killed by SIGPIPE, and let the exit-time flush of
        # what is still buffered go nowhere instead of failing again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return EXIT_BROKEN_PIPE
    except OSError as error:
        if error.errno == errno.ENAMETOOLONG:
            errorfile.report(name_too_long_line(error))
            return EXIT_USAGE
        if error.errno not in NO_SPACE:
            errorfile.record_exception(error)
            raise
        errorfile.report(no_space_line(error))  # a failure: the supervisor waits if the run's disks are full
        return EXIT_FAILED
    except Exception as error:  # a bug: it keeps its traceback, and torchrun and the supervisor learn what it was
        if (signum := stop_signal(error)) is not None:
            return stopped(signum)
        errorfile.record_exception(error)
        raise


def _dispatch(args: argparse.Namespace) -> int:
    if args.command == "train":
        config = _run_config(args)
        from ftrain.config import for_launch, make_local_directories, remove_if_empty

        for_launch(config, int(os.environ.get("WORLD_SIZE", "1")))  # checked here, before the storage is taken
        name_process(rank_role("worker"), config.name)
        watch_launcher()

        with imports():
            from ftrain.train.trainer import train
            from ftrain.train.user_code import check

        trackers = config.log.trackers() if os.environ.get("RANK", "0") == "0" else []  # rank 0 alone tracks
        check(config.env, config.hooks, trackers)  # refused here, before any rendezvous or the storage is taken
        made = make_local_directories(config)
        try:
            code = train(config)
        finally:
            remove_if_empty(made)
        if code in STOPPED and not os.environ.get(SUPERVISOR_ENV) and os.environ.get("RANK", "0") == "0":
            print(f"[ftrain] {CONTINUE}", flush=True)  # a supervisor says it for its workers, once it stops too
        return code
    if args.command == "supervise":
        from ftrain.supervise.options import SupervisorOptions
        from ftrain.supervise.supervisor import supervise

        options = SupervisorOptions(**{f.name: getattr(args, f.name) for f in dataclasses.fields(SupervisorOptions)})
        train_args = [args.config, *(["--storage", args.storage] if args.storage is not None else []), *args.overrides]
        config = _run_config(args)
        from ftrain.supervise.user_check import check_in_child, has_user_code

        trackers = config.log.trackers()
        if has_user_code(config.env, config.hooks, trackers):  # checked in a child, before anything is taken
            check_in_child(config.env, config.hooks, trackers)
        name_process("supervisor", config.name)
        return supervise(options, config, train_args)
    if args.command == "bench":
        from ftrain.tools.bench import run_benchmark

        return run_benchmark(args.iterations, args.settings)
    from ftrain.config import check_options_used, storage_options

    options = storage_options(args.storage_option)
    check_options_used(args.storage_option, [args.run if args.command == "plot" else args.url])
    if args.command == "ckpt":
        from ftrain.ckpt import commands as ckpt_commands

        if args.ckpt_command == "ls":
            return ckpt_commands.ls(args.url, options)
        if args.ckpt_command == "verify":  # the checkpoints, then the policy snapshots, which are verified alike
            from ftrain.ckpt.format import parse_checkpoint_url
            from ftrain.policy import snapshots

            if snapshots.parse_snapshot_url(args.url) is not None:
                return snapshots.verify(args.url, options)
            checkpoints = ckpt_commands.verify(args.url, options)
            whole = parse_checkpoint_url(args.url)[1] is None
            return max(checkpoints, snapshots.verify(args.url, options) if whole else 0)
        if args.ckpt_command == "show":
            return ckpt_commands.show(args.url, options, as_json=args.json)
        if args.ckpt_command == "unquarantine":
            return ckpt_commands.unquarantine(args.url, options)
        if args.keep_line is not None:
            rules = {"--keep-last": args.keep_last, "--keep-best": args.keep_best, "--best-metric": args.best_metric}
            rules |= {"--keep-every": args.keep_every, "--pin": args.pin or None, "--drop-bad": args.drop_bad or None}
            if given := [option for option, value in rules.items() if value is not None]:
                raise UserError(
                    f"--keep-line keeps one line of descent instead of the retention rules: {', '.join(given)} would "
                    "do nothing beside it: run the two as two commands"
                )
            return ckpt_commands.keep_line(args.url, args.keep_line, options, force=args.force, dry_run=args.dry_run)
        return ckpt_commands.prune(
            args.url,
            keep_last=args.keep_last,
            keep_best=args.keep_best,
            best_metric=args.best_metric,
            keep_every=args.keep_every,
            pinned=args.pin,
            dry_run=args.dry_run,
            drop_bad=args.drop_bad,
            options=options,
            force=args.force,
        )
    if args.command == "play":
        from ftrain.policy.options import check_play_options

        check_play_options(args.episodes, args.seed, args.video)  # before torch's imports
        with imports():
            from ftrain.policy.load import load_policy
            from ftrain.policy.play import play

        policy = load_policy(args.url, options, log=_stderr)
        play(policy, args.episodes, deterministic=not args.stochastic, video=args.video, seed=args.seed)
        return 0
    if args.command == "export":
        from ftrain.policy.options import export_format

        fmt = export_format(args.format, args.output)  # before torch's imports and the policy's download
        with imports():
            from ftrain.policy.export import export
            from ftrain.policy.load import load_policy

        export(load_policy(args.url, options, log=_stderr), fmt, args.output)
        return 0
    if args.command == "plot":
        from ftrain.tools.plot import plot_run

        plot_run(args.run, args.output, options)
        return 0
    raise AssertionError(args.command)


def _run_config(args: argparse.Namespace) -> Config:
    """The config of ``train`` and ``supervise``, validated before anything starts: its env id too, against
    gymnasium's registry (not in ``config.py``, which the supervisor imports and which stays free of gymnasium)."""
    from ftrain.ckpt.format import CHECKPOINTS
    from ftrain.ckpt.spool import check_place as check_spool_place
    from ftrain.ckpt.steps import (
        check_checkpoint_url,
        check_not_a_checkpoints_directory,
        check_outside_steps,
        check_steps_place,
        check_storage_place,
    )
    from ftrain.ckpt.storage import Storage
    from ftrain.config import check_options_used, check_writable, load_config, local_path
    from ftrain.train.env_ids import check_env_id

    config = load_config(args.config, args.overrides, args.storage)
    resumed_from = config.resume if config.resume not in ("auto", "never") else ""
    check_options_used(getattr(args, "storage_option", []), [config.storage.url, resumed_from, config.teacher])
    check_env_id(config.env)
    check_storage_place(config.storage.url)
    storage = local_path(config.storage.url)
    if config.log_dir:  # not inside a step that its run's retention deletes (the storage itself: checked above)
        check_outside_steps(Path(config.log_dir), "log_dir")
    check_spool_place(config)
    own = bool(storage) and os.path.isdir(os.path.join(storage, CHECKPOINTS))  # steps of its own: it goes on from them
    if os.path.isdir(storage):  # before a supervisor writes its logs there
        check_not_a_checkpoints_directory(Storage.open(storage))
        check_steps_place(storage)
    fix = "make it writable (its permissions, its mount), or pass --storage another directory"
    if own:  # else its saves would fail and hold
        check_writable(Path(storage, CHECKPOINTS), "--storage", fix)
    for place, option in ((storage, "--storage"), (config.log_dir, "log_dir=")):  # before a lease, a log or a pool
        if place and os.path.isdir(place):  # (one that cannot be made is said where it is made)
            check_writable(Path(place), option, fix if option == "--storage" else "")

    def checkpoint_at(key: str, value: str, path: str) -> None:
        try:
            check_checkpoint_url(path)
        except UserError as error:
            raise UserError(f"{key}={value}: {error}") from None

    resume = local_path(config.resume) if config.resume not in ("auto", "never") else ""
    if resume and storage and not own:  # else it needs the step it began at: a run's storage that holds none is none
        checkpoint_at("resume", config.resume, resume)
    distills = config.algorithm.class_name == "Distillation" and config.teacher
    teacher = local_path(config.teacher) if distills else ""
    if teacher and storage and not own and not resume and not os.path.exists(teacher):  # else a resumed student's
        checkpoint_at("teacher", config.teacher, teacher)  # checkpoint holds its teacher; one there is checked at load
    return config


def _escape_what_stdout_cannot_encode() -> None:
    """On a stdout that is not UTF-8 (an ASCII terminal), a path in ü prints as \\xfc: not a UnicodeEncodeError after
    training. A UTF-8 one is left as it is (a warm pool's worker may not reconfigure its inherited stdout)."""
    stdout = sys.stdout
    if isinstance(stdout, io.TextIOWrapper) and codecs.lookup(stdout.encoding).name != "utf-8":
        with contextlib.suppress(OSError, ValueError):
            stdout.reconfigure(errors="backslashreplace")


def _stdout_reader_gone() -> bool:
    """Whether stdout is a pipe nobody reads any more (the kernel flags its write end with POLLERR)."""
    poll = select.poll()
    poll.register(sys.stdout.fileno(), select.POLLOUT)
    return any(events & select.POLLERR for _, events in poll.poll(0))


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)
