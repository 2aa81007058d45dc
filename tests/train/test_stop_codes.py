"""A stop by a signal saves and says so in the exit code, 128 + the signal (130 for SIGINT, 143 for SIGTERM), in
every process that can tell: a lone ``ftrain train``, torchrun as the supervisor runs it (signalled itself, or its
workers signalled as a scheduler does), ``ftrain supervise``. Real processes, real training, real signals."""

from __future__ import annotations

import json
import math
import os
import pty
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ftrain.ckpt.steps import select_resume
from ftrain.ckpt.storage import Storage
from ftrain.errors import ONE_STOP, STOPPED
from ftrain.heartbeat import ENV_DIR, read_heartbeats
from ftrain.supervise.attempt import TORCHRUN

from helpers import (
    AS_A_BACKGROUND_JOB,
    REPO,
    SMOKE,
    TESTS,
    as_a_terminal_starts_it,
    child_env,
    events,
    final_manifest,
    finish,
    hooks_override,
    launch,
    manifests,
    metrics_by_iteration,
    probe_hook,
    run_train,
    supervise_command,
    train_command,
    training,
    wait_for,
)

pytestmark = pytest.mark.slow

LONG = "iterations=100000"
STOPS = [signal.SIGINT, signal.SIGTERM]


def start(command: list[str], heartbeats: Path, **popen: object) -> subprocess.Popen:
    """``popen``: more of Popen's arguments. A test worker may ignore SIGINT (pytest-xdist's do), and a child keeps
    that until it sets a handler of its own: one that sends SIGINT before the trainer does resets it first."""
    return launch(
        command,
        cwd=REPO,
        env=child_env({ENV_DIR: str(heartbeats)}),
        stdin=subprocess.DEVNULL,  # not the test worker's (pytest-xdist's channel): once a traceback here read from it
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
        **popen,
    )


def test_a_lone_trainer_stopped_by_ctrl_c_saves_and_exits_130(tmp_path) -> None:
    storage = tmp_path / "run"
    proc = start([*train_command(storage, LONG), "log.console=true"], tmp_path / "beats")
    training(tmp_path / "beats", 3, [0])
    proc.send_signal(signal.SIGINT)
    assert finish(proc) == 130
    step = final_manifest(storage)["step"]
    assert 3 <= step < 100000
    printed = proc.stdout.read()
    assert f"[ftrain] stopped by SIGINT: saved step {step}, exiting with code 130" in printed, printed[-2000:]
    assert printed.splitlines()[-1] == "[ftrain] run the same command again to continue", printed[-2000:]


@pytest.mark.parametrize("launcher", ["train", "supervise", "ftrun"])
def test_a_closed_terminal_sighup_saves_and_exits_143_as_sigterm(tmp_path, launcher: str) -> None:
    """SIGHUP, a terminal or SSH session that closed, killed the run where it stood (a probe lost 9 iterations and
    left a step half written), and ftrun exited 129: now it stops as SIGTERM does, saving every iteration trained,
    exit 143."""
    storage, supervised = tmp_path / "run", launcher == "supervise"
    command, beats = [*train_command(storage, LONG), "log.console=true"], tmp_path / "beats"
    if supervised:
        command, beats = supervise_command(storage, LONG, ranks=1), storage / "heartbeat"
    elif launcher == "ftrun":
        command = [sys.executable, "-m", TORCHRUN, "--standalone", "--nproc-per-node=1", *command[1:]]
    proc = start(command, beats, preexec_fn=as_a_terminal_starts_it)
    training(beats, 3, [0])
    proc.send_signal(signal.SIGHUP)
    assert finish(proc) == 143
    printed, step = proc.stdout.read(), final_manifest(storage)["step"]
    assert step == max(metrics_by_iteration(storage)) >= 3, "every iteration trained is in the last save"
    said = "SIGHUP: asking the workers to save" if supervised else f"stopped by SIGTERM: saved step {step}"
    assert said in printed, printed[-2000:]


def in_a_terminal(command: list[str], *, ignore_sighup: bool = False) -> tuple[subprocess.Popen, int]:
    """``command`` started with a real terminal (a pseudo-terminal that is its controlling one) as its stdin, stdout
    and stderr, as in a shell; ``ignore_sighup``: as ``disown`` or ``trap '' HUP`` leave it. Returns the process and
    the terminal's other side: closing that closes the terminal."""
    master, slave = pty.openpty()
    terminal = os.ttyname(slave)

    def become_its_session() -> None:
        as_a_terminal_starts_it()
        os.setsid()
        opened = os.open(terminal, os.O_RDWR)  # the first terminal a session leader opens becomes its controlling one
        for fd in (0, 1, 2):
            os.dup2(opened, fd)
        if ignore_sighup:
            signal.signal(signal.SIGHUP, signal.SIG_IGN)

    proc = subprocess.Popen(command, cwd=REPO, env=child_env(), preexec_fn=become_its_session, close_fds=True)
    os.close(slave)
    return proc, master


def read_until(master: int, wanted: bytes, timeout: float = 120) -> bytes:
    printed, deadline = b"", time.monotonic() + timeout
    while wanted not in printed and time.monotonic() < deadline:
        printed += os.read(master, 65536)
    return printed


@pytest.mark.parametrize("launcher", ["train", "supervise"])
def test_a_run_printing_to_a_terminal_that_closes_saves_and_exits_143(tmp_path, launcher: str) -> None:
    """A real terminal closes while the run prints its progress to it: the kernel sends SIGHUP, and every write to it
    fails (EIO), which ended a lone run (exit 1) before its save, and a supervised worker that printed before the
    supervisor passed the SIGHUP on. Now what they still print goes to /dev/null, and the run saves every iteration
    trained and exits 143."""
    storage, overrides = tmp_path / "run", (LONG, "checkpoint.interval=100000", "log.console=true")
    command = train_command(storage, *overrides)
    if launcher == "supervise":
        command = supervise_command(storage, *overrides, ranks=1)
    proc, terminal = in_a_terminal(command)
    printed = read_until(terminal, b"it 5/")
    os.close(terminal)  # the terminal closes
    assert proc.wait(timeout=120) == 143, printed[-2000:]
    step = final_manifest(storage)["step"]
    assert step == max(metrics_by_iteration(storage)) >= 5, "every iteration trained is in the last save"


@pytest.mark.parametrize("launcher", ["train", "supervise"])
def test_a_run_that_ignores_sighup_outlives_its_terminal_and_finishes(tmp_path, launcher: str) -> None:
    """A run that SIGHUP does not stop (``disown``, ``trap '' HUP``) goes on printing to a terminal that closed: every
    write failed (EIO), and the process that wrote (a worker, the supervisor) ended with exit 1, losing what it had
    trained since its last save. Now what it prints goes to /dev/null, and it trains to the end."""
    storage, iterations = tmp_path / "run", 300
    overrides = (f"iterations={iterations}", "checkpoint.interval=100", "log.console=true")
    command = train_command(storage, *overrides)
    if launcher == "supervise":
        command = supervise_command(storage, *overrides, ranks=1)
    proc, terminal = in_a_terminal(command, ignore_sighup=True)
    printed = read_until(terminal, b"it 5/")
    os.close(terminal)
    assert finish(proc, timeout=180) == 0, printed[-2000:]
    assert final_manifest(storage)["step"] == max(metrics_by_iteration(storage)) == iterations


@pytest.mark.parametrize(
    ("target", "stop", "code", "as_supervised"),
    [
        ("torchrun", signal.SIGINT, 130, False),
        ("torchrun", signal.SIGTERM, 143, True),
        ("workers", signal.SIGTERM, 143, True),
    ],
)
def test_ftrain_torchrun_passes_the_stop_code_on(tmp_path, target, stop, code, as_supervised) -> None:
    """A signal to torchrun (it stops its workers with it: Ctrl-C in a terminal reaches torchrun only) or to every
    worker (a scheduler's preemption): the workers save and exit 128 + the signal, and so does torchrun, run by hand
    or as the supervisor runs it (``--failures``: the workers' account goes to that file)."""
    storage, beats = tmp_path / "run", tmp_path / "beats"
    failures = tmp_path / "failures.json"
    command = train_command(storage, LONG, ranks=2)
    at = command.index("--standalone")
    options = [f"--failures={failures}"] if as_supervised else []
    proc = start([sys.executable, "-m", TORCHRUN, *options, *command[at:]], beats)
    training(beats, 3, [0, 1])
    pids = [proc.pid] if target == "torchrun" else [beat.pid for beat in read_heartbeats(beats).values()]
    for pid in pids:
        os.kill(pid, stop)
    assert finish(proc) == code, (proc.stdout.read()[-3000:], failures.exists() and failures.read_text())
    assert {beat.phase for beat in read_heartbeats(beats).values()} == {"preempted"}
    assert final_manifest(storage)["step"] >= 3
    if target == "workers":
        assert {failure["exitcode"] for failure in json.loads(failures.read_text()).values()} == {143}


def test_ftrain_supervise_exits_130_after_ctrl_c_with_the_real_trainer(tmp_path) -> None:
    storage = tmp_path / "run"
    command = [sys.executable, "-m", "ftrain", "supervise", "--nproc-per-node", "2", SMOKE, "--storage", str(storage)]
    proc = start([*command, LONG, "log.console=false"], tmp_path / "unused")
    training(storage / "heartbeat", 3, [0, 1])
    proc.send_signal(signal.SIGINT)
    assert finish(proc) == 130
    assert [event["event"] for event in events(storage)][-2:] == ["preempted", "summary"]
    printed, step = proc.stdout.read(), final_manifest(storage)["step"]
    assert "ftrain supervise: interrupted (exit 130): 0 restarts, 0 iterations lost" in printed
    again = f"ftrain supervise: interrupted: the workers saved (newest step {step}); run the same command again to"
    assert again in printed and printed.count("run the same command again") == 1, printed  # the workers do not say it
    assert step >= 3
    # the workers got SIGTERM from the supervisor (a SIGINT would reach a warm worker twice), and name the user's Ctrl-C
    said = f"[ftrain] stopped by SIGINT to the supervisor (Ctrl-C), passed on as SIGTERM: saved step {step}, exiting "
    assert printed.count(said) == 1, printed


@pytest.mark.parametrize("supervised", [False, True], ids=["train", "supervise"])
def test_a_stop_delivered_again_at_once_is_one_stop_that_saves(tmp_path, supervised: bool) -> None:
    """``timeout`` passes a signal it gets to its command and then to the command's whole process group: the command
    gets it twice, microseconds apart, and where its handler ran in between (a supervisor asleep in its poll) that
    was Ctrl-C twice: a probe's supervisor SIGKILLed torchrun and lost two iterations. Twice a random 20-100 ms apart
    (under ``errors.ONE_STOP``), in iterations long enough that the second comes before the save: one stop, every
    iteration trained saved, exit 130."""
    storage, draw = tmp_path / "run", random.Random(int(supervised))
    slow = [LONG, "env.num_envs=32", "num_steps_per_env=64", "log.console=true"]  # iterations long enough to stop in
    if supervised:
        command, beats = [*supervise_command(storage, *slow, ranks=1)], storage / "heartbeat"
    else:
        command, beats = [*train_command(storage, *slow)], tmp_path / "beats"
    proc = start(command, beats)
    training(beats, draw.randint(3, 8), [0])
    proc.send_signal(signal.SIGINT)
    time.sleep(draw.uniform(0.02, 0.1))
    proc.send_signal(signal.SIGINT)
    assert finish(proc) == 130
    printed, step = proc.stdout.read(), final_manifest(storage)["step"]
    assert step == max(metrics_by_iteration(storage)), "every iteration trained is in the last save"
    assert "did not all confirm a save" not in printed and "killed by SIGKILL" not in printed, printed[-2000:]
    said = f"stopped by SIGINT{' to the supervisor (Ctrl-C), passed on as SIGTERM' * supervised}: saved step {step}"
    assert said in printed, printed[-2000:]


def test_a_stop_at_any_moment_of_the_start_is_one_line_and_its_exit_code(tmp_path) -> None:
    """While it imports torch and builds the run (seconds on a slow machine) a Ctrl-C or SIGTERM is one line, not a
    traceback (Ctrl-C) or a silent death (SIGTERM, a probe's); from the moment the trainer takes them over it saves
    first. So for ``ftrun`` (torchrun's agent: a traceback from its import of torch or its rendezvous, before). Random
    moments over the whole start and one at 8 s (training), each signal to each launcher at least once: 128 + the
    signal every time, no traceback, a line that says the stop, and whatever the storage holds verifies; or, within
    the interpreter's own start, its own end with nothing made (``_the_interpreters_own_end``)."""
    draw = random.Random(130)
    interpreter_start = _interpreter_start()
    # log-uniform: the start's phases are shorter the earlier they come (imports, rendezvous, building, training)
    moments = [*sorted(math.exp(draw.uniform(math.log(0.05), math.log(10.0))) for _ in range(5)), 8.0]
    pairs = [(stop, ftrun) for stop in STOPS for ftrun in (False, True)]
    pairs += [(draw.choice(STOPS), draw.random() < 0.5) for _ in range(len(moments) - len(pairs))]
    draw.shuffle(pairs)
    saved, checked = 0, []
    for moment, (stop, ftrun) in zip(moments, pairs, strict=True):
        checked.append(f"{stop.name} to {'ftrun' if ftrun else 'train'} at {moment:.2f} s")
        storage = tmp_path / f"run-{moment:.2f}"
        command, beats = [*train_command(storage, LONG), "log.console=true"], tmp_path / f"beats-{moment:.2f}"
        if ftrun:
            command = [sys.executable, "-m", TORCHRUN, "--standalone", "--nproc-per-node=1", *command[1:]]
        proc = start(command, beats, preexec_fn=as_a_terminal_starts_it)
        time.sleep(moment)
        proc.send_signal(stop)
        output = proc.communicate(timeout=120)[0]
        if moment < interpreter_start and _the_interpreters_own_end(proc.returncode, stop, output, storage):
            checked[-1] += " (in the interpreter's own start)"
            continue
        _assert_said_its_stop(proc.returncode, stop, output, moment)
        if committed := manifests(storage):  # the newest committed step is the one a resume takes: it verifies
            assert select_resume(Storage.open(str(storage)), log=lambda line: None)[0] == max(committed), moment
            saved += 1
    print(
        f"{len(checked)} stops checked ({', '.join(checked)}), {saved} after a save (the interpreter's own end "
        f"allowed before {interpreter_start:.2f} s)"
    )


def test_a_stop_while_any_command_imports_is_one_line(tmp_path) -> None:
    """Every command imports for a while before it runs (its own modules, then torch: seconds on a slow machine). A
    Ctrl-C or SIGTERM then, at any moment after the interpreter's own start, ends it with the stop's one line and 128
    + the signal, from every entry: the scripts ``ftrain`` and ``ftrun``, and ``python -m`` of either (Python's
    traceback from a module's import, or its silent death by SIGTERM, before); and none is lost (one in about 60
    trained on: ``test_a_stop_whose_exception_was_swallowed_still_stops_the_run``). Random moments over the imports,
    a random signal and entry each."""
    scripts, draw, checked = Path(sys.executable).parent, random.Random(131), []
    entries = {
        "ftrain": [str(scripts / "ftrain")],
        "python -m ftrain": [sys.executable, "-m", "ftrain"],
        "ftrun": [str(scripts / "ftrun"), "--standalone", "--nproc-per-node=1", "-m", "ftrain"],
        f"python -m {TORCHRUN}": [sys.executable, "-m", TORCHRUN, "--standalone", "--nproc-per-node=1", "-m", "ftrain"],
    }
    interpreter_start = _interpreter_start()
    drawn = [*sorted(entries), *(draw.choice(sorted(entries)) for _ in range(2))]  # each entry, and two more
    for case, entry in enumerate(drawn):
        moment, stop = draw.uniform(interpreter_start, interpreter_start + 0.4), draw.choice(STOPS)
        checked.append(f"{stop.name} to {entry} at {moment:.2f} s")
        command = [*entries[entry], *train_command(tmp_path / f"run-{case}", LONG)[3:]]
        proc = start(command, tmp_path / f"beats-{case}", preexec_fn=as_a_terminal_starts_it)
        time.sleep(moment)
        proc.send_signal(stop)
        output = proc.communicate(timeout=120)[0]
        _assert_said_its_stop(proc.returncode, stop, output, moment)
    print(f"{len(checked)} stops checked: {', '.join(checked)}")


def _interpreter_start() -> float:
    """Twice the time Python takes, today (loaded or not), to start and import ``ftrain.entry``, the one module the
    commands import before their stop guard: a stop before that is the interpreter's to handle."""
    return 2 * max(_seconds([sys.executable, "-c", "import ftrain.entry"]) for _ in range(3))


def _the_interpreters_own_end(code: int, stop: signal.Signals, output: str, storage: Path) -> bool:
    """A stop before any code of ftrain's ran ends as Python ends it: by the signal (SIGTERM; SIGINT before Python's
    handler), after Python's own traceback through its start (runpy's, site's: exit 1 where site did not import), no
    frame of ftrain's in it but the package's ``__init__``, and nothing made."""
    ours = set(re.findall(rf'File "{re.escape(str(REPO / "ftrain"))}/([^"]+)"', output))
    return code in (-stop, 1) and ours <= {"__init__.py"} and not storage.exists()


def _assert_said_its_stop(code: int, stop: signal.Signals, output: str, moment: float) -> None:
    assert code == 128 + stop, (moment, stop, output[-2000:])
    assert "Traceback" not in output and "death signal" not in output, (moment, output[-2000:])
    said = ["ftrain: interrupted (Ctrl-C)" if stop == signal.SIGINT else "ftrain: stopped by SIGTERM"]
    said += [f"stopped by {stop.name} while starting", f"stopped by {stop.name}: saved step"]
    assert any(line in output for line in said), (moment, stop, output[-2000:])


def _seconds(command: list[str]) -> float:
    began = time.monotonic()
    subprocess.run(command, check=True)
    return time.monotonic() - began


CTRL_C_INSIDE_MUJOCOS_IMPORT = """
import os, signal, sys
class CtrlC:
    def find_spec(self, name, path, target=None):
        if name == "mujoco._structs":
            os.kill(os.getpid(), signal.SIGINT)
sys.meta_path.insert(0, CtrlC())
"""
"""A finder that sends this process a real SIGINT when MuJoCo's compiled ``_specs`` module, in its initialisation,
imports ``_structs``: pybind11 turns the KeyboardInterrupt into an ImportError, and gymnasium that into "MuJoCo is not
installed"."""


def test_ctrl_c_inside_a_compiled_modules_import_is_the_same_one_line(tmp_path) -> None:
    """One CI run sent its Ctrl-C at 0.27 s, inside MuJoCo's import, and got a traceback ending in gymnasium's
    "MuJoCo is not installed" (exit 1). The heavy imports hold a Ctrl-C until they are done; one that still comes
    out of an import wrapped in another exception (a module imported later, the user's robot's) is told by its cause."""
    assert _train_after(CTRL_C_INSIDE_MUJOCOS_IMPORT, tmp_path) == (130, "ftrain: interrupted (Ctrl-C)\n")
    chain = "while error:\n  print(type(error).__name__, stop_signal(error) == 2)\n  error = error.__cause__\n"
    wrapped = "from ftrain.errors import stop_signal\n"
    wrapped += "try:\n import gymnasium.envs.mujoco\nexcept Exception as e:\n error = e\n"
    wrapped += chain + "try:\n import no_such_module_here\nexcept Exception as e:\n error = e\n" + chain
    told = subprocess.run(
        [sys.executable, "-c", CTRL_C_INSIDE_MUJOCOS_IMPORT + wrapped], capture_output=True, text=True
    )
    lines = ["DependencyNotInstalled True", "ImportError True", "KeyboardInterrupt True", "ModuleNotFoundError False"]
    assert told.stdout.splitlines() == lines, told.stderr


SIGTERM_TO_THE_GROUP_WHILE_GLFW_PROBES = """
import os, signal, subprocess, sys
class ProbeKilled:
    def find_spec(self, name, path, target=None):
        if name == "glfw.library":
            communicate = subprocess.Popen.communicate
            def killed(self, *args, **kwargs):
                os.killpg(0, signal.SIGTERM)
                return communicate(self, *args, **kwargs)
            subprocess.Popen.communicate = killed
sys.meta_path.insert(0, ProbeKilled())
"""
"""A finder that, while pyGLFW (which gymnasium's MuJoCo imports) runs a child process per library it finds to read
its version, sends SIGTERM to the process group each time, as torchrun stops its workers (``killpg``) or a terminal
its foreground: the child dies, and pyGLFW raises "Failed to load GLFW3 shared library"."""


def test_a_stop_that_fails_an_import_is_the_stop(tmp_path) -> None:
    """The heavy imports hold a stop until they are done; one that also ends a library's child (signalled with its
    group) fails the import, and a CI run printed that ImportError's traceback. The stop is what ended it: its one
    line and code."""
    assert _train_after(SIGTERM_TO_THE_GROUP_WHILE_GLFW_PROBES, tmp_path) == (143, "ftrain: stopped by SIGTERM\n")
    assert not (tmp_path / "run").exists()


SIGTERM_SWALLOWED = """
import os, signal, sys, time
class Swallowing:
    def find_spec(self, name, path, target=None):
        if name == "yaml":
            sys.meta_path.remove(self)
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(5)
            except BaseException as error:
                print("swallowed", type(error).__name__, file=sys.stderr)
sys.meta_path.insert(0, Swallowing())
"""
"""A finder that sends this process a SIGTERM while YAML imports, and swallows what it raises, as a library's ``except
BaseException`` does, or C code that clears errors (a dict lookup calling a ``__eq__`` of Python's): one stop in
about 60 at random moments of a start was lost so, and the run trained on."""


@pytest.mark.parametrize("command", ["train", "supervise", "ftrun"])
def test_a_stop_whose_exception_was_swallowed_still_stops_the_run(tmp_path, command) -> None:
    """Where the trainer, the supervisor or torchrun's agent takes the signals over, it raises the stop again."""
    said = _train_after(SIGTERM_SWALLOWED, tmp_path, command)
    assert said == (143, "swallowed Terminated\nftrain: stopped by SIGTERM\n")
    assert not manifests(tmp_path / "run")


def test_a_stop_swallowed_in_a_short_command_ends_it_as_stopped(tmp_path) -> None:
    """A command that never takes its signals over (``ckpt ls``) does its work, then ends with the stop it lost
    (``entry.run_command``), not with 0 as if nothing had come."""
    run_train(tmp_path / "run", "iterations=1")
    code, said = _command_after(SIGTERM_SWALLOWED, tmp_path, "ftrain", ["ckpt", "ls", str(tmp_path / "run")])
    lines = said.splitlines()  # stdout's and stderr's lines, in either order
    assert code == 143 and lines.count("ftrain: stopped by SIGTERM") == 1 and "swallowed Terminated" in lines, said
    assert any(re.fullmatch(r" +1 +committed .* newest", line) for line in lines), said  # it did its work


def _train_after(prelude: str, tmp_path: Path, command: str = "train") -> tuple[int, str]:
    """``ftrain train`` a long run (or ``ftrain supervise``, or ``ftrun`` of one rank), in a Python that runs
    ``prelude`` first: its exit code and output."""
    arguments = (supervise_command if command == "supervise" else train_command)(tmp_path / "run", LONG)[3:]
    if command == "ftrun":
        arguments = ["--standalone", "--nproc-per-node=1", "-m", "ftrain", *arguments]
    return _command_after(prelude, tmp_path, TORCHRUN if command == "ftrun" else "ftrain", arguments)


def _command_after(prelude: str, tmp_path: Path, module: str, arguments: list[str]) -> tuple[int, str]:
    """``python -m module arguments`` in a Python that runs ``prelude`` first: its exit code and output."""
    run = f'import runpy; runpy.run_module("{module}", run_name="__main__", alter_sys=True)'
    command = [sys.executable, "-c", prelude + run, *arguments]
    proc = start(command, tmp_path / "beats", preexec_fn=as_a_terminal_starts_it)
    output = proc.communicate(timeout=120)[0]
    return proc.returncode, output


def test_the_supervisors_closing_line_names_the_step_a_rerun_resumes_from(tmp_path) -> None:
    """Whatever stops it (SIGTERM, two quick Ctrl-Cs, SIGTERM right after a worker's SIGKILL), the closing line's
    newest step is the storage's, not the workers' last heartbeat, which misses a commit made as they stop. Random
    schedules, the real trainer under ``ftrain supervise``, saving every 3 iterations."""
    draw = random.Random(143)
    kinds = ["sigterm", "two-sigints", "kill-then-sigterm"]
    schedules = [*draw.sample(kinds, len(kinds)), draw.choice(kinds)]
    for number, schedule in enumerate(schedules):
        storage = tmp_path / f"run-{number}"
        command = [
            sys.executable,
            "-m",
            "ftrain",
            "supervise",
            "--nproc-per-node",
            "2",
            SMOKE,
            "--storage",
            str(storage),
        ]
        proc = start([*command, LONG, "checkpoint.interval=3", "log.console=false"], tmp_path / "unused")
        beats = training(storage / "heartbeat", draw.randint(4, 12), [0, 1])
        if schedule == "kill-then-sigterm":
            os.kill(beats[draw.randint(0, 1)].pid, signal.SIGKILL)
            time.sleep(draw.uniform(0.2, 1.5))
        proc.send_signal(signal.SIGINT if schedule == "two-sigints" else signal.SIGTERM)
        if schedule == "two-sigints":  # pressed twice: more than errors.ONE_STOP apart (closer, one stop sent twice)
            time.sleep(draw.uniform(ONE_STOP + 0.1, 1.5))
            proc.send_signal(signal.SIGINT)
        assert finish(proc) in STOPPED, schedule
        closing = re.findall(
            r"ftrain supervise: (?:preempted|interrupted): .*\(newest step (\d+)\); run the same command again to ",
            proc.stdout.read(),
        )
        newest = select_resume(Storage.open(str(storage)), log=lambda line: None)[0]
        assert closing == [str(newest)], (schedule, closing, newest)
    print(f"{len(schedules)} schedules checked: {', '.join(schedules)}")


def test_a_stop_that_comes_after_the_last_step_ends_a_finished_run_with_0(tmp_path) -> None:
    """A SIGTERM that reaches the supervisor once every worker has finished (a scheduler's time limit, a preemption,
    moments late) cut nothing short: the run ends finished, exit 0, not preempted with 143 (on which a SLURM script
    requeues a finished job). The supervisor is held (SIGSTOP) from its workers' first iteration until they are done,
    and the SIGTERM waits for it."""
    storage = tmp_path / "run"
    proc = start(supervise_command(storage, "iterations=20"), tmp_path / "unused")
    wait_for(lambda: len(read_heartbeats(storage / "heartbeat")) == 2, "both workers training")
    proc.send_signal(signal.SIGSTOP)
    try:
        wait_for(
            lambda: {beat.phase for beat in read_heartbeats(storage / "heartbeat").values()} == {"done"},
            "both workers done",
        )
        proc.send_signal(signal.SIGTERM)
    finally:
        proc.send_signal(signal.SIGCONT)
    assert finish(proc) == 0
    printed = proc.stdout.read()
    assert "ftrain supervise: training finished (exit 0)" in printed and "preempted" not in printed, printed[-2000:]
    assert "training finished (step 20; the stop came after the last step)" in printed, printed[-2000:]
    assert [event["event"] for event in events(storage)][-2:] == ["done", "summary"]
    assert final_manifest(storage)["step"] == 20


def test_a_sigint_ignored_at_start_stays_ignored_and_sigterm_is_taken_over(tmp_path) -> None:
    """A script's background job starts with SIGINT ignored, so that a Ctrl-C at the terminal stops the script's
    foreground, not the job; Python leaves it so, and so do a run's stop request (it took SIGINT over) and the workers
    the supervisor forks from its warm pool (they got Python's start-up handler back)."""
    probe = (
        "import signal; from ftrain.train.stop import StopRequest; StopRequest().install(); "
        "print(signal.getsignal(signal.SIGINT) is signal.SIG_IGN, signal.getsignal(signal.SIGTERM) is signal.SIG_DFL)"
    )
    for prefix, ignored in ((AS_A_BACKGROUND_JOB, "True"), ([], "False")):
        done = subprocess.run(
            [*prefix, sys.executable, "-c", probe],
            capture_output=True,
            text=True,
            timeout=60,
            preexec_fn=as_a_terminal_starts_it,
        )
        assert done.stdout.split() == [ignored, "False"], done.stdout + done.stderr
    said = tmp_path / "sigint.txt"
    hook = hooks_override(probe_hook("SigintHook", path=said))
    command = [*AS_A_BACKGROUND_JOB, *supervise_command(tmp_path / "run", "iterations=1", hook)]
    done = subprocess.run(
        command, cwd=REPO, env=child_env({"PYTHONPATH": str(TESTS)}), capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0 and said.read_text() == "ignored\n" * 2, done.stderr + said.read_text()
