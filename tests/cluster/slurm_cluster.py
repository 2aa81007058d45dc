"""A private SLURM cluster on this machine for the tests: one ``slurmctld`` and one ``slurmd`` per simulated node,
all on 127.0.0.1, with their own munge daemon, key and socket, configuration, spool and state in one directory. Every
SLURM command gets ``SLURM_CONF`` of this cluster (the daemons ``-f``), so a SLURM configured on the machine is never
touched; ``stop()`` ends every process of the cluster and of its jobs and removes the directory.

Job records: no ``slurmdbd`` (it needs a MySQL server), so no ``sacct``. ``JobCompType=jobcomp/filetxt`` appends a
line to ``jobcomp.txt`` at every end of a job (a requeue too: the state it goes on in, PENDING), and
``scontrol show job`` keeps the job (``MinJobAge``) with its state, restart count and exit code: together what
``sacct`` would say."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from ftrain import procfs

from s3_outage import free_port

T = TypeVar("T")
COMMANDS = ("munged", "slurmctld", "slurmd", "sbatch", "scontrol")
CPUS = 16
"""CPUs each node declares (``SlurmdParameters=config_overrides`` believes it, whatever the machine has): as many
as ``launch/slurm.sbatch`` asks for by default."""
CLUSTER_ENV = "FTRAIN_TEST_SLURM"
NODE_ENV = "FTRAIN_TEST_SLURM_NODE"
"""Set in the daemons' environment (the first reaches every ``slurmstepd`` and job process, the second only the node's
``slurmd``): how ``stop`` and ``kill_node`` find this cluster's processes among the machine's."""


def missing() -> str | None:
    """Why the cluster cannot run here, or None."""
    absent = [name for name in COMMANDS if shutil.which(name) is None]
    if absent:
        return f"{', '.join(absent)} not installed (apt-get install slurm-wlm munge; launch/setup.sh does it as root)"
    if os.geteuid() != 0:
        return "the private SLURM runs its daemons as root (SlurmUser=root): run the tests as root"
    return None


def slurm_conf(root: Path, nodes: list[str]) -> str:
    """Everything under ``root``; each node a ``slurmd`` on 127.0.0.1 with a port of its own."""
    lines = [
        "ClusterName=ftraintest",
        "SlurmctldHost=localhost(127.0.0.1)",
        f"SlurmctldPort={free_port()}",
        "SlurmUser=root",
        "SlurmdUser=root",
        "AuthType=auth/munge",
        "CredType=cred/munge",
        f"AuthInfo=socket={root}/munge/socket,cred_expire=5",  # a requeued job waits this long (default 120 s)
        f"StateSaveLocation={root}/state",
        f"SlurmdSpoolDir={root}/spool/%n",
        f"SlurmctldPidFile={root}/slurmctld.pid",
        f"SlurmdPidFile={root}/slurmd-%n.pid",
        f"SlurmctldLogFile={root}/slurmctld.log",
        f"SlurmdLogFile={root}/slurmd-%n.log",
        "ProctrackType=proctrack/linuxproc",
        "TaskPlugin=task/none",
        "SelectType=select/cons_tres",
        "SelectTypeParameters=CR_CPU",
        "SchedulerParameters=sched_interval=2",  # a requeued job starts once eligible, not at the next minute
        "MpiDefault=none",
        "SwitchType=switch/none",
        "JobRequeue=1",
        "ReturnToService=2",  # a node whose slurmd starts again is back in service
        "SlurmdTimeout=10",  # a node whose slurmd is gone is DOWN after 10 s
        "KillWait=15",  # SIGTERM to SIGKILL when a job ends: saves of smoke-sized runs take a second
        "MinJobAge=3600",
        "JobCompType=jobcomp/filetxt",
        f"JobCompLoc={root}/jobcomp.txt",
        "JobAcctGatherType=jobacct_gather/none",
        "AccountingStorageType=accounting_storage/none",
        "SlurmdParameters=config_overrides",
    ]
    lines += [f"NodeName={node} NodeAddr=127.0.0.1 Port={free_port()} CPUs={CPUS} State=UNKNOWN" for node in nodes]
    lines.append("PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP")
    return "\n".join(lines) + "\n"


def fields(record: str) -> dict[str, str]:
    """``Key=Value`` pairs of a one-line SLURM record (``scontrol -o show ...``, a jobcomp line)."""
    return dict(re.findall(r"(\w+)=(\S*)", record))


class SlurmCluster:
    """Nodes ``n1``...``nN`` on 127.0.0.1 under a temporary directory: ``start()``, then ``sbatch`` and ``job``."""

    def __init__(self, nodes: int) -> None:
        # munged wants every directory above its socket searchable by all: not under pytest's private tmp_path
        self.root = Path(tempfile.mkdtemp(prefix="ftrain-slurm-"))
        self.root.chmod(0o755)
        self.nodes = [f"n{i}" for i in range(1, nodes + 1)]
        self.conf = self.root / "slurm.conf"
        self.env = {"SLURM_CONF": str(self.conf), CLUSTER_ENV: str(self.root)}
        """What every command and daemon of the cluster gets on top of its environment."""

    def start(self) -> None:
        munge = self.root / "munge"
        (munge / "key").mkdir(parents=True, mode=0o700)
        munge.chmod(0o755)
        key = munge / "key" / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        for name in ("state", "spool"):
            (self.root / name).mkdir()
        self.conf.write_text(slurm_conf(self.root, self.nodes))
        self._daemon(
            "munged",
            f"--socket={munge}/socket",
            f"--key-file={key}",
            f"--log-file={munge}/munged.log",
            f"--pid-file={munge}/munged.pid",
            f"--seed-file={munge}/munged.seed",
        )
        self._daemon("slurmctld", "-f", str(self.conf))
        for node in self.nodes:
            self.start_node(node)
        self.wait(lambda: self.idle() == set(self.nodes), "every node idle", timeout=60)

    def start_node(self, node: str) -> None:
        """Start (again) ``node``'s ``slurmd``."""
        self._daemon("slurmd", "-f", str(self.conf), "-N", node, env={NODE_ENV: node})

    def _daemon(self, *command: str, env: dict | None = None) -> None:
        """A daemon that forks into the background once it is up."""
        log = self.root / f"{command[0]}.out"
        with log.open("ab") as out:
            subprocess.run(command, env=self.environment(env), stdout=out, stderr=out, check=True, timeout=60)

    def environment(self, env: dict | None = None) -> dict:
        """This process's environment, then ``env``, then the cluster's (a SLURM_CONF of the machine never wins)."""
        return {**os.environ, **(env or {}), **self.env}

    def run(self, *command: str, cwd: Path | None = None, env: dict | None = None) -> str:
        """A SLURM command's output, on this cluster; a command that fails fails the test."""
        done = subprocess.run(command, cwd=cwd, env=self.environment(env), capture_output=True, text=True, timeout=60)
        if done.returncode != 0:
            raise RuntimeError(f"{' '.join(command)} exited {done.returncode}: {done.stderr}")
        return done.stdout

    def idle(self) -> set[str]:
        return set(self.run("sinfo", "--noheader", "--states=idle", "--format=%n").split())

    def sbatch(self, *args: str, cwd: Path, env: dict | None = None) -> int:
        """Submit a batch job from ``cwd`` (its working directory) with ``env`` (which the job inherits); its id."""
        return int(self.run("sbatch", "--parsable", *args, cwd=cwd, env=env).split(";")[0])

    def job(self, job_id: int) -> dict[str, str]:
        """``scontrol show job``: JobState, Restarts, ExitCode, NodeList, ..."""
        return fields(self.run("scontrol", "--oneliner", "show", "job", str(job_id)))

    def ends(self, job_id: int) -> list[dict[str, str]]:
        """The job's jobcomp records, oldest first: one per end of one of its starts."""
        path = self.root / "jobcomp.txt"
        lines = path.read_text().splitlines() if path.exists() else []
        return [record for record in map(fields, lines) if record["JobId"] == str(job_id)]

    def wait_state(self, job_id: int, *states: str, timeout: float = 300) -> dict[str, str]:
        """The job once it is in one of ``states``."""
        return self.wait(lambda: (job := self.job(job_id))["JobState"] in states and job, f"job in {states}", timeout)

    def down(self) -> list[str]:
        """Nodes not in service (their ``slurmd`` gone, or not back yet)."""
        return self.run("sinfo", "--noheader", "--states=down,drain,fail", "--format=%n").split()

    def cancel_all(self) -> None:
        """Cancel every job still known and wait until none runs: the next test starts on an idle cluster."""
        self.run("scancel", "--partition=test")
        self.wait(lambda: not self.run("squeue", "--noheader").strip(), "no job left", timeout=120)

    def wait(self, predicate: Callable[[], T], what: str, timeout: float) -> T:
        """``predicate()`` once it is true; a cluster that does not get there fails the test, naming its logs."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if value := predicate():
                return value
            time.sleep(0.5)
        raise AssertionError(f"private SLURM: timed out after {timeout} s waiting for {what} (logs in {self.root})")

    def kill_node(self, node: str) -> None:
        """``node`` dies: SIGKILL to its ``slurmd``, its ``slurmstepd`` processes and every process of a job below
        them, at once and until none is left."""
        self._kill(lambda: self._node_processes(node))

    def _node_processes(self, node: str) -> set[int]:
        """``node``'s ``slurmd``, the job processes SLURM started there (``SLURMD_NODENAME``) and their
        ``slurmstepd`` parents."""
        ours = self._processes()
        tasks = set(procfs.with_environment("SLURMD_NODENAME", node)) & ours
        parents = {int(stat[1]) for stat in map(procfs.stat_fields, tasks) if stat}
        stepds = {pid for pid in parents if procfs.read(pid, "cmdline").startswith(b"slurmstepd")}
        return (set(procfs.with_environment(NODE_ENV, node)) & ours) | tasks | stepds

    def stop(self) -> None:
        """Every daemon and job process of the cluster gone, its directory removed."""
        self._kill(self._processes)
        shutil.rmtree(self.root)

    def _processes(self) -> set[int]:
        return set(procfs.with_environment(CLUSTER_ENV, str(self.root)))

    def _kill(self, find: Callable[[], set[int]]) -> None:
        while pids := {pid for top in find() for pid in [top, *procfs.descendants(top)]}:
            for pid in pids:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            time.sleep(0.1)
