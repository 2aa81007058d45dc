"""The split update's teams: the first half of the ranks learns the actor, the second half the critic.

Each team learns its model on the whole batch, data-parallel within the team (every member takes its share of each
minibatch, and the team averages the gradients over its own process group, through shared memory where its ranks
share a machine); the teams meet to gather the rollout and to exchange their models, once per iteration each.
torchrun numbers a node's ranks consecutively, so on two nodes each team is one node, and the update's meetings per
minibatch never leave it. A model's weights travel with Adam's state for them, in Adam's own layout.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn

from ftrain.comm.collectives import Comm, Traffic
from ftrain.comm.group import RankInfo
from ftrain.config import Config


class Role(enum.Enum):
    """The model a team learns; its value is the team's number."""

    ACTOR = 0
    CRITIC = 1


@dataclass(frozen=True)
class Team:
    role: Role
    ranks: list[int]
    """Global ranks of this team, in order; the first one speaks for it."""
    other: list[int]
    """The other team's ranks."""
    rank: int
    """This rank's global rank."""
    comm: Comm
    """The team's collectives: its own process group, and its shared memory where its ranks share a machine."""

    @property
    def index(self) -> int:
        """This rank's place in the team: which share of each minibatch it learns from."""
        return self.ranks.index(self.rank)

    @property
    def size(self) -> int:
        return len(self.ranks)

    @property
    def partner(self) -> int:
        """The rank at this rank's place in the other team (the adaptive schedule's KL goes actor to critic)."""
        return self.other[self.index]

    def send_kl(self, kl_mean: torch.Tensor) -> dist.Work:
        """An actor's rank: a minibatch's KL to its partner, without waiting (``wait()`` the result before the end)."""
        return dist.isend(kl_mean.view(1).clone(), dst=self.partner)

    def receive_kl(self) -> torch.Tensor:
        """A critic's rank: the minibatch's KL from its partner (which is ahead: it learns the larger model)."""
        kl_mean = torch.empty(1)
        dist.recv(kl_mean, src=self.partner)
        return kl_mean[0]


def splits_update(config: Config, info: RankInfo) -> bool:
    """Whether the ranks split the update into two teams (``split_update``, an even number of ranks)."""
    return config.split_update and info.world_size >= 2 and info.world_size % 2 == 0


def build_team(config: Config, info: RankInfo, comm: Comm, traffic: Traffic) -> Team | None:
    """This rank's team (every rank calls it at the same point), or None where the update is not split.
    ``traffic``: what a team member sends its team (one model's gradients with the KL and the losses)."""
    if not splits_update(config, info):
        return None
    half = info.world_size // 2
    teams = [list(range(half)), list(range(half, info.world_size))]
    number = 0 if info.rank < half else 1
    own = comm.team(teams, traffic, config.dist_timeout)
    return Team(Role(number), teams[number], teams[1 - number], info.rank, own)


def adam_record(optimizer: torch.optim.Adam, params: list[nn.Parameter]) -> torch.Tensor:
    """Weights of ``params`` and Adam's state for them (both moments and the step count), flat."""
    parts = []
    for param in params:
        state = optimizer.state[param]
        parts += [param.detach(), state["exp_avg"], state["exp_avg_sq"], state["step"]]
    return torch.cat([part.reshape(-1) for part in parts])


def record_size(params: list[nn.Parameter]) -> int:
    return sum(3 * param.numel() + 1 for param in params)


def load_adam_record(optimizer: torch.optim.Adam, params: list[nn.Parameter], record: torch.Tensor) -> None:
    """The inverse of :func:`adam_record`; Adam's state is created, as its first step would, where absent."""
    offset = 0
    with torch.no_grad():
        for param in params:
            state = optimizer.state[param]
            if not state:
                state.update(step=torch.zeros((), dtype=torch.float32), exp_avg=torch.zeros_like(param))
                state["exp_avg_sq"] = torch.zeros_like(param)
            for target in (param, state["exp_avg"], state["exp_avg_sq"], state["step"]):
                target.view(-1).copy_(record[offset : offset + target.numel()])
                offset += target.numel()
