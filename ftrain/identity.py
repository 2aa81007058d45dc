"""What names a run: a run id, a generation and an attempt. Everything else that names a run derives from these.

- The **run id** is chosen once and kept across restarts and requeues (``run_id``). An id that torchrun gives every
  run (``none`` without ``--rdzv-id``) is never taken: two plain ``torchrun`` runs must not pass for one.
- The **generation** numbers the holders of the run's storage. It only grows, and the storage's lease
  (``ckpt/lease.py``) hands it out: +1 for another run, for the same run id once none of its processes lives (a
  requeued job, the same command again), and for every new plan of a run on several nodes (node 0's supervisor
  started again, a run started anew on etcd). Every commit carries it and is refused below the lease's
  (``ckpt/fence.py``).
- The **attempt** numbers the launches of torchrun within a generation (``supervise/plan.py``). On several nodes,
  a commit is also refused below the newest (generation, attempt) that committed: a node cut off from the others
  still runs an older attempt.

Derived from them: the fence record, the plan (its generation is the one its maker took; requests of another
generation do nothing), torchrun's rendezvous id, the attempt token that finds an attempt's processes, the attempt's
log directory, and each manifest's ``run_id``, ``generation`` and ``attempt``. The log directory is the storage's
(one run per log directory: its supervisor, or rank 0 without one, holds a lock), and the tracker run is saved with
the checkpoints.
"""

from __future__ import annotations

import hashlib
import os
import secrets
from dataclasses import dataclass

SHARED_IDS = frozenset({"", "none"})
"""``TORCHELASTIC_RUN_ID``s that name no run: torchrun's default ``--rdzv-id`` is ``none`` for every run."""
RUN_ID_ENV = "FTRAIN_RUN_ID"
"""The run id: set by ``ftrain supervise`` for its workers, or by the user to name a run (e.g. a batch job id that
survives a requeue)."""
GENERATION_ENV = "FTRAIN_GENERATION"
"""The generation this process's commits are checked against, set by whoever holds the lease for it."""
ATTEMPT_ENV = "FTRAIN_ATTEMPT"
"""The attempt within the generation; set on several nodes, where attempts of one generation may overlap."""
ENV_NAMES = (RUN_ID_ENV, GENERATION_ENV, ATTEMPT_ENV)


def run_id(secret: bytes | None = None, endpoint: tuple[str, int] | None = None) -> str:
    """``FTRAIN_RUN_ID``; else, with the ``secret`` that the supervisors of several nodes share, a digest of it and
    node 0's rendezvous ``endpoint`` (every node computes the same); else torchrun's run id
    (``TORCHELASTIC_RUN_ID``, from ``--rdzv-id``) unless it is one every run shares (``SHARED_IDS``); else a new
    random one (an unsupervised run: its rank 0 draws it, the other ranks get it from there, ``ckpt/claim.py``)."""
    if os.environ.get(RUN_ID_ENV):
        return os.environ[RUN_ID_ENV]
    if secret is not None:
        return hashlib.sha256(b"ftrain-run:" + secret + repr(endpoint).encode()).hexdigest()[:16]
    torchrun = os.environ.get("TORCHELASTIC_RUN_ID", "")
    return torchrun if torchrun.strip().lower() not in SHARED_IDS else secrets.token_hex(8)


@dataclass(frozen=True)
class Identity:
    """Who commits: ``attempt`` is None where attempts do not overlap (one node; a run without a supervisor)."""

    run_id: str
    generation: int
    attempt: int | None = None

    def env(self) -> dict[str, str]:
        """The environment that hands this identity to child processes (an empty attempt: none)."""
        attempt = str(self.attempt) if self.attempt is not None else ""
        return {RUN_ID_ENV: self.run_id, GENERATION_ENV: str(self.generation), ATTEMPT_ENV: attempt}

    @classmethod
    def from_env(cls) -> Identity | None:
        """This process's identity; None where no lease was taken for it (a process outside any run: a tool, a
        test)."""
        run, generation = os.environ.get(RUN_ID_ENV), os.environ.get(GENERATION_ENV, "")
        attempt = os.environ.get(ATTEMPT_ENV, "")
        if not run or not generation.isdigit():
            return None
        return cls(run, int(generation), int(attempt) if attempt.isdigit() else None)


def saved_environ() -> dict[str, str | None]:
    """This process's identity variables as they are now, for ``restore_environ``."""
    return {name: os.environ.get(name) for name in ENV_NAMES}


def restore_environ(saved: dict[str, str | None]) -> None:
    """The identity variables as ``saved_environ`` found them: a later run in this process is another one."""
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value
