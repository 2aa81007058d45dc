"""One history per storage: every manifest names its ``parent``, the state its commit continued (``{"step",
"state_sha256"}`` of the step its holder resumed from or committed before; None for a fresh start), and a storage's
verified steps must form one line of descent.

The line ends at the head, the newest step of the newest generation (the lease's fencing token, ``identity.py``; on
several nodes, then of the newest attempt), and runs back through each step's parent; a parent that retention deleted is
passed over (the next older step is taken as its ancestor). A verified step off the line is:
- **superseded** if an older generation (or attempt) committed it: a commit that landed after a newer one had gone on
  from an earlier step (the one-request window of ``fence.py`` on object stores). The newer generation's line wins:
  resume never takes it, and the holder's start sets it aside;
- a **fork** if the head's own generation and attempt committed it: two processes wrote one history as one run. Resume
  refuses the storage until a person keeps one line (``ftrain ckpt prune --keep-line STEP``).
Manifests from before lineage (no ``parent`` key) are taken to continue the next older step. Imports: ``format``,
``errors``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from ftrain.ckpt.format import VERIFIED, StepInfo
from ftrain.errors import UserError, command


@dataclass(frozen=True)
class History:
    """The verified steps of a storage, newest first in each list."""

    line: list[int]
    """The head's line of descent."""
    superseded: list[int]
    """Steps of an older generation than the head's, off its line."""
    forks: list[int]
    """Steps of the head's generation off its line."""
    generation: tuple[int, int] = (0, -1)
    """The head's generation and attempt (``generation``)."""

    def off_line(self) -> list[int]:
        return sorted(self.superseded + self.forks, reverse=True)

    def fork_message(self, url: str) -> str:
        """The one line that refuses a forked storage, and says how to keep one line."""
        keep = command("ftrain", "ckpt", "prune", url, "--keep-line", "STEP")
        return (
            f"{url} holds two histories of generation {self.generation[0]}: steps {listed_steps(self.line)} and "
            f"steps {listed_steps(self.forks)} do not descend from each other (two processes wrote it as one run); "
            f"keep one line with {keep} (the other's steps are set aside under quarantine/), then start again"
        )


def generation(info: StepInfo) -> tuple[int, int]:
    """Who committed ``info``, in the order of the fence (``fence.py``): its generation, then (on several nodes) its
    attempt within it."""
    manifest = info.manifest or {}
    attempt = manifest.get("attempt")
    return int(manifest.get("generation") or 0), int(attempt) if attempt is not None else -1


def history(infos: Iterable[StepInfo], head: int | None = None) -> History:
    """The history of the verified steps among ``infos``; ``head``: the step whose line to follow (default: the
    newest step of the newest generation)."""
    verified = sorted((i for i in infos if i.status == VERIFIED and i.manifest), key=lambda i: i.step, reverse=True)
    if not verified:
        return History([], [], [])
    top = max(verified, key=lambda i: (generation(i), i.step)) if head is None else _find(verified, head)
    line, superseded, forks = [top.step], [], []
    current = top
    for info in verified:
        if info is top:
            continue
        if info.step < top.step and _continues(current, info):
            line.append(info.step)
            current = info
        else:
            (superseded if generation(info) < generation(top) else forks).append(info.step)
    return History(line, superseded, forks, generation(top))


def _continues(child: StepInfo, older: StepInfo) -> bool:
    """Whether ``older`` is ``child``'s parent, or (the parent deleted since) may be its ancestor."""
    if "parent" not in child.manifest:  # written before lineage: taken as continuing the step before it
        return True
    parent = child.manifest["parent"]
    if parent is None:  # a fresh start: nothing before it is its history
        return False
    if parent["step"] != older.step:
        return parent["step"] > older.step
    digest = parent.get("state_sha256")
    return digest is None or digest == older.manifest.get("state_sha256")


def _find(verified: list[StepInfo], step: int) -> StepInfo:
    for info in verified:
        if info.step == step:
            return info
    steps = listed_steps(info.step for info in verified)
    raise UserError(f"step {step} is not a committed step of this storage: pick one of {steps}")


def listed_steps(steps: Iterable[int]) -> str:
    listed = sorted(steps, reverse=True)
    return ", ".join(map(str, listed[:6])) + (f" (and {len(listed) - 6} more)" if len(listed) > 6 else "")
