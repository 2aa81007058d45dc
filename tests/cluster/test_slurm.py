"""``launch/slurm.sbatch`` as written, on a private SLURM cluster (``slurm_cluster.py``): real slurmctld, slurmd and
munged, real srun, torchrun and workers, the signals SLURM itself sends. Each job runs on 2 of the 3 nodes with one
rank per node (``--cpus-per-task=1``); the assertions read SLURM's own records (``scontrol show job``, the jobcomp
file) and the storage (every committed step verifies; the final state is the state of the same run outside SLURM)."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from ftrain import procfs
from ftrain.heartbeat import Heartbeat, read_heartbeats

from helpers import REPO, SMOKE, TESTS, child_env, events, final_manifest, hooks_override, probe_hook, wait_for
from slurm_cluster import SlurmCluster

pytestmark = [
    pytest.mark.slow,
    pytest.mark.slurm,
    pytest.mark.skipif(
        not (REPO / ".venv" / "bin" / "ftrain").exists(),
        reason="launch/slurm.sbatch runs .venv/bin/ftrain of the directory it is submitted from: run launch/setup.sh",
    ),
]

ITERATIONS = 100
INTERVAL = 20
OVERRIDES = (f"iterations={ITERATIONS}", f"checkpoint.interval={INTERVAL}", "dist_timeout=10")


def pace(seconds: float) -> str:
    """Iterations of at least ``seconds``: a run that lasts while SLURM stops and moves it (state is unchanged)."""
    return hooks_override(probe_hook("PacingHook", seconds=seconds))


@pytest.fixture
def reference(reference_state) -> str:
    """The state of the same run outside SLURM: torchrun, 2 ranks, no interruption."""
    return reference_state(ITERATIONS)


def submit(
    slurm: SlurmCluster,
    storage: Path,
    *sbatch: str,
    seconds: float = 0.1,
    supervise: tuple[str, ...] = (),
    env: dict | None = None,
) -> int:
    """``sbatch [sbatch options] launch/slurm.sbatch [supervise options] configs/smoke.yaml --storage STORAGE ...``
    from the repo."""
    options = ["--cpus-per-task=1", f"--output={storage}.out", *sbatch]
    command = [*options, "launch/slurm.sbatch", *supervise, SMOKE, "--storage", str(storage), *OVERRIDES]
    env = child_env({"PYTHONPATH": str(TESTS), **(env or {})})
    return slurm.sbatch(*command, pace(seconds), cwd=REPO, env=env)


def both_nodes_training(storage: Path, iteration: int = 10) -> dict[int, tuple[int, Heartbeat]]:
    """Once both nodes (one rank each) train a world of 2 past ``iteration``: rank -> (its node's number, from its
    heartbeat directory: SLURM's node id with c10d, etcd's number with etcd; its heartbeat)."""

    def ready() -> dict[int, tuple[int, Heartbeat]] | None:
        found = {}
        for directory in storage.glob("heartbeat/node-*"):
            for beat in read_heartbeats(directory).values():
                if beat.world == 2 and beat.iteration >= iteration and beat.phase in ("rollout", "update"):
                    found[beat.rank] = (int(directory.name.removeprefix("node-")), beat)
        return found if len(found) == 2 else None

    return wait_for(ready, f"both nodes at iteration {iteration}")


def slurm_node(pid: int) -> str:
    """The SLURM node a job process runs on (``SLURMD_NODENAME``, which slurmd puts in every task's environment)."""
    variables = procfs.read(pid, "environ").split(b"\0")
    return next(v.split(b"=", 1)[1].decode() for v in variables if v.startswith(b"SLURMD_NODENAME="))


def finished(slurm: SlurmCluster, job_id: int, storage: Path) -> dict[str, str]:
    """The job's record once it ended; a job that did not complete fails the test with its output."""
    job = slurm.wait_state(job_id, "COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", timeout=400)
    assert job["JobState"] == "COMPLETED" and job["ExitCode"] == "0:0", f"{job}\n{Path(f'{storage}.out').read_text()}"
    return job


def assert_every_step_verifies(storage: Path) -> None:
    verify = subprocess.run([sys.executable, "-m", "ftrain", "ckpt", "verify", str(storage)], cwd=REPO, env=child_env())
    assert verify.returncode == 0


def assert_verified_and_equal(storage: Path, reference: str) -> None:
    """Every committed step verifies, and the final one is step ITERATIONS with the reference state."""
    assert_every_step_verifies(storage)
    manifest = final_manifest(storage)
    assert (manifest["step"], manifest["state_sha256"]) == (ITERATIONS, reference)


def assert_nothing_lost(storage: Path) -> None:
    """Every iteration ran exactly once (metrics.csv has a row per iteration run; a redone one would repeat), and
    every supervisor's summary says 0 iterations lost."""
    with (storage / "metrics.csv").open() as file:
        iterations = [int(row["iteration"]) for row in csv.DictReader(file)]
    assert iterations == list(range(1, len(iterations) + 1)), "an iteration was run twice"
    assert all(event["iterations_lost"] == 0 for event in events(storage) if event["event"] == "summary")


def starts(storage: Path, node: int = 0) -> list[int | None]:
    """The step each start of node ``node``'s supervisor resumed from (None: fresh)."""
    return [e["step"] for e in events(storage) if e["event"] == "resumed" and e["node"] == node]


def test_a_job_trains_on_two_nodes_as_one_world_and_ends_completed(slurm, reference, tmp_path):
    storage = tmp_path / "run"
    job = finished(slurm, submit(slurm, storage, seconds=0), storage)
    assert (job["Restarts"], job["NumNodes"], job["NumTasks"]) == ("0", "2", "2")
    assert [end["JobState"] for end in slurm.ends(job["JobId"])] == ["COMPLETED"]
    assert {e["node"] for e in events(storage) if e["event"] == "done"} == {0, 1}
    assert final_manifest(storage)["world_size"] == 2
    assert_verified_and_equal(storage, reference)


def test_scontrol_requeue_saves_requeues_and_continues_with_nothing_lost(slurm, reference, tmp_path):
    storage = tmp_path / "run"
    job_id = submit(slurm, storage)
    both_nodes_training(storage)
    slurm.run("scontrol", "requeue", str(job_id))
    job = finished(slurm, job_id, storage)
    assert job["Restarts"] == "1"
    assert [end["JobState"] for end in slurm.ends(job_id)] == ["PENDING", "COMPLETED"]  # requeued, then done
    assert [e["node"] for e in events(storage) if e["event"] == "preempted"] in ([0, 1], [1, 0])
    fresh, resumed = starts(storage)
    assert fresh is None and 10 <= resumed < ITERATIONS and resumed % INTERVAL, "resumed from the step saved on stop"
    assert_nothing_lost(storage)
    assert_verified_and_equal(storage, reference)


def test_scancel_saves_and_the_job_is_not_requeued(slurm, tmp_path):
    storage = tmp_path / "run"
    job_id = submit(slurm, storage)
    both_nodes_training(storage)
    slurm.run("scancel", str(job_id))
    slurm.wait(lambda: len([e for e in events(storage) if e["event"] == "summary"]) == 2, "both summaries", 120)
    job = slurm.wait_state(job_id, "CANCELLED", "PENDING", "RUNNING", "COMPLETED")
    assert (job["JobState"], job["Restarts"], job["ExitCode"]) == ("CANCELLED", "0", "0:15")  # SIGTERM ended it
    assert [end["JobState"] for end in slurm.ends(job_id)] == ["CANCELLED"]
    summaries = [e for e in events(storage) if e["event"] == "summary"]
    assert [e["code"] for e in summaries] == [143, 143]  # both supervisors: saved on SIGTERM
    with (storage / "metrics.csv").open() as file:
        last = max(int(row["iteration"]) for row in csv.DictReader(file))
    assert final_manifest(storage)["step"] == last < ITERATIONS  # the newest iteration saved: nothing lost
    assert_nothing_lost(storage)


def test_the_time_limit_signal_saves_requeues_and_the_job_completes_with_nothing_lost(slurm, reference, tmp_path):
    """``--time=2 --signal=TERM@60``: slurmctld checks time limits every 30 s, so the signal comes within the first
    60 s of a start; a run of over 70 s gets it at least once (and maybe again in a later start)."""
    storage = tmp_path / "run"
    job_id = submit(slurm, storage, "--time=2", "--signal=TERM@60", seconds=0.7)
    job = finished(slurm, job_id, storage)
    restarts = int(job["Restarts"])
    assert restarts >= 1
    assert [end["JobState"] for end in slurm.ends(job_id)] == ["PENDING"] * restarts + ["COMPLETED"]
    out = Path(f"{storage}.out").read_text()
    # a signal as the run ended (its supervisors done, srun's step cancelled around them): one more start, which
    # finds nothing to train and completes the job (the script cannot tell from srun's code that both ended with 0)
    late = out.count("; nothing to train: pass iterations=N") // 2
    assert late <= 1 and len([e for e in events(storage) if e["event"] == "preempted"]) == 2 * (restarts - late)
    assert "requeueing job" in out  # the script requeued it, not SLURM
    assert_nothing_lost(storage)
    assert_verified_and_equal(storage, reference)


def test_a_lost_node_requeues_the_job_which_continues_on_the_nodes_left(slurm, reference, tmp_path):
    """n2 dies (its slurmd and every process of the job on it); SLURM marks it DOWN, requeues the job (--requeue),
    which starts again on n1 and n3 from the newest verified step: the same world size, so the same final state."""
    storage = tmp_path / "run"
    job_id = submit(slurm, storage)
    both_nodes_training(storage, INTERVAL + 5)  # a step committed
    slurm.kill_node("n2")
    job = finished(slurm, job_id, storage)
    assert job["Restarts"] == "1" and "n2" not in slurm.run("scontrol", "show", "hostnames", job["NodeList"])
    assert [end["JobState"] for end in slurm.ends(job_id)][-1] == "COMPLETED"
    fresh, resumed = starts(storage)[0], starts(storage)[-1]
    assert fresh is None and resumed >= INTERVAL
    assert_verified_and_equal(storage, reference)


@pytest.mark.parametrize("rendezvous", ["c10d", "etcd"])
def test_an_elastic_job_trains_on_when_a_node_dies(slurm, rendezvous, request, tmp_path):
    """``FTRAIN_NNODES=1:2 sbatch --no-kill``: a node dies, the job keeps the other, which trains on alone to the end.
    The node that dies is n2, not the batch host: when the batch host dies, slurmctld sometimes kills the job's
    step on the other node too (its log: ``batch step received ... This should never happen``), which no trainer
    survives. c10d: n2 is node 1 (node 0 must live). etcd (``FTRAIN_ETCD``): n2 hosts rank 0 or rank 1, as torch
    orders one host name's nodes by torchrun's pid; losing rank 0's node, which hosts the workers' store, is
    ``test_elastic.py``'s case outside SLURM."""
    storage = tmp_path / "run"
    env = {"FTRAIN_NNODES": "1:2"}
    if rendezvous == "etcd":
        env["FTRAIN_ETCD"] = request.getfixturevalue("etcd_server")
    job_id = submit(slurm, storage, "--no-kill", supervise=("--rejoin-timeout=3",), env=env)
    beats = both_nodes_training(storage, INTERVAL + 5)
    job = slurm.job(job_id)
    (victim,) = set(slurm.run("scontrol", "show", "hostnames", job["NodeList"]).split()) - {job["BatchHost"]}
    lost_rank = next(rank for rank, (_, beat) in beats.items() if slurm_node(beat.pid) == victim)
    (lost, _), (kept, _) = beats[lost_rank], beats[1 - lost_rank]
    slurm.kill_node(victim)
    job = finished(slurm, job_id, storage)
    assert (job["Restarts"], job["NodeList"]) == ("0", job["BatchHost"])  # not requeued: the allocation shrank
    assert [(e["node"], e["code"]) for e in events(storage) if e["event"] == "summary"] == [(kept, 0)]
    manifest = final_manifest(storage)
    assert manifest["step"] == ITERATIONS and [world for _, world in manifest["world_sizes"]] == [2, 1]
    (resize,) = [e for e in events(storage) if e["event"] == "resize" and e["node"] == kept]
    assert (resize["old_world"], resize["new_world"], resize["why"]) == (2, 1, f"node {lost} lost"), resize
    assert resize["lost"] <= INTERVAL, resize
    assert_every_step_verifies(storage)
