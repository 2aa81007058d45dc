"""The shared-memory all-reduce between ranks of one host, on 2 to 4 real torchrun ranks."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ftrain.comm.shm_allreduce import PREFIX, _owner_tag
from ftrain.comm.shm_allreduce import _shared_dir as sweep_dir
from ftrain.procfs import descendants

from helpers import REPO, child_env

TIMEOUT = 5.0
"""The reducer's timeout in these runs: a dead peer must end the others within it."""
EXITED, SILENT = "a peer rank exited during an all-reduce", f"no answer from the other ranks within {TIMEOUT:.0f} s"


@pytest.mark.slow  # ranks under torchrun
@pytest.mark.parametrize("ranks", [2, 3, 4])
def test_shared_memory_all_reduce_is_exact_leaves_nothing_and_a_dead_peer_ends_the_others(tmp_path, ranks) -> None:
    """The sum of every rank's buffer in rank order, the same bits on every rank; gloo's own bits at two ranks, where
    the order of a sum of two cannot matter. At three ranks or more gloo sums each chunk of a buffer in another order
    (its ring starts at another rank for each chunk, and it changes algorithm with the world size): the same sum to
    rounding, not the same bits. (At one rank nothing is reduced: the reducer is built only for a world of two or
    more.)"""
    out = tmp_path / "report.json"
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={ranks}"]
    done = subprocess.run(
        [*launcher, str(REPO / "tests" / "comm" / "shm_worker.py"), str(out), str(TIMEOUT)],
        cwd=REPO,
        env=child_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    reports = {}
    for rank in range(ranks - 1):  # the last rank dies once the sums are checked
        report = out.with_name(f"{out.name}.{rank}")
        assert report.exists(), f"rank {rank} wrote no report:\n{done.stderr[-3000:]}"
        reports[rank] = json.loads(report.read_text())
    assert len({report["digest"] for report in reports.values()}) == 1, "every rank must get the same bits"
    for rank, report in reports.items():
        assert report["exact"], f"rank {rank}: the shared-memory sum must be the rank-ordered sum, bit for bit"
        assert report["copies"], f"rank {rank}: all_gather and broadcast_ must hand on every bit, as gloo's do"
        assert report["close"], f"rank {rank}: the shared-memory sum must equal gloo's to rounding"
        assert report["like_gloo"] or ranks > 2, f"rank {rank}: gloo's bits at two ranks"
        assert report["leftovers"] == [], "segment and pipes must be unlinked once every rank has opened them"
        # two ranks: the survivor's inbox has no writer left, an end of file at once; more: the others still write to
        # it, so the dead peer's silence is noticed when the reducer's timeout runs out, as gloo's would be
        assert report["peer_lost"] in (EXITED, SILENT), report
        assert report["seconds"] < (3 if ranks == 2 else TIMEOUT + 5), f"rank {rank}: {report['seconds']:.1f} s"


@pytest.mark.slow  # ranks under torchrun
def test_a_rank_killed_inside_the_set_up_leaves_names_that_the_next_start_on_the_host_sweeps(tmp_path) -> None:
    """Rank 0 SIGKILLed after it created the segment and the pipes and before their unlink (it waits in the set-up's
    first barrier for a rank that holds back): its names outlive the run, and the next reducer set up on this host
    removes them, and only them (a live process's names stay)."""
    launcher = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node=2"]
    run = subprocess.Popen(
        [*launcher, str(REPO / "tests" / "comm" / "shm_setup_worker.py")],
        cwd=REPO,
        env=child_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    live = Path(sweep_dir()) / f"{PREFIX}{_owner_tag(os.getpid())}-0123456789ab.shm"  # this process's: it lives
    live.touch()
    try:
        deadline, orphans = time.monotonic() + 60, []
        while not orphans and time.monotonic() < deadline:
            workers = set(descendants(run.pid))
            orphans = [p for p in Path(sweep_dir()).glob(f"{PREFIX}*") if int(p.name.split("-")[2]) in workers]
            time.sleep(0.05)
        assert len(orphans) == 3, f"rank 0 made a segment and two pipes: {orphans}"  # ranks 0 and 1's pipes
        creator = int(orphans[0].name.split("-")[2])
        os.kill(creator, signal.SIGKILL)
        for pid in [run.pid, *descendants(run.pid)]:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        run.wait(timeout=30)
        assert all(path.exists() for path in orphans), "names left behind by the kill (the case the sweep is for)"
        next_start = subprocess.run(  # the next reducer on this host: the same set-up, with a peer that comes
            [*launcher, str(REPO / "tests" / "comm" / "shm_worker.py"), str(tmp_path / "report.json"), str(TIMEOUT)],
            cwd=REPO,
            env=child_env(),
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert (tmp_path / "report.json.0").exists(), next_start.stderr[-3000:]
        assert [path for path in orphans if path.exists()] == [], "the next start must sweep a dead creator's names"
        assert live.exists(), "the names of a process that lives must stay"
    finally:
        live.unlink(missing_ok=True)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(run.pid, signal.SIGKILL)
