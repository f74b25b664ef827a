"""What every learner family builds (``Learner``) and the pieces their update phases share.

An update phase trains every member at once on its own transitions. Every loss term is one
value per member (``[R]``); a step minimises their sum, so each member's gradient is its own,
and Adam (element-wise, ``learners.optim``) updates each member as if it were alone. A member
whose loss or parameters become NaN or infinite is reported after the phase; the engine
freezes it (the phase's ``freeze``): its parameters and optimiser state are zeroed and its loss
terms masked out, so it stays finite and fixed while the others go on.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Protocol

import torch
from tensordict import TensorDictBase

from collectors import ReplayMemory
from learners.networks import member_state_dict
from learners.optim import MemberAdam
from losses.common import PRIORITY_WEIGHT_KEY


@dataclass
class Optimisers:
    actor: MemberAdam  # the actor's parameters (and SAC's per-member temperature)
    critic: MemberAdam  # the critic's (or Q-networks')


class UpdatePhase(Protocol):
    """What the engine calls between episodes (``learners.monte_carlo.learner.PhaseRunner``,
    ``learners.td.learner.TDPhaseRunner``)."""

    active: torch.Tensor  # [R], 0 for a frozen member
    critic_metrics: tuple[str, ...]  # the diagnostics' names (metrics.csv's critic/... columns)
    actor_metrics: tuple[str, ...]
    # what computes the critic's and the actor's steps ("fused": plain-tensor steps with the loss module's
    # numbers; "loss module") and, when not fused, why: summary.json's "paths"
    path: dict
    code_refusal: str | None  # the loss's own code or settings keep the fused steps off: said in one line
    fast_path_code: tuple[str, ...] = ()  # the qualified-name prefixes of its fast path's own code (learners.fast_paths)

    def run(self, data: TensorDictBase, minibatch_size: int, totals: "MetricTotals",
            episode: int = 0) -> dict[int, str]:
        """Train on ``data`` ([R, n]) before or after episode ``episode``; {member: reason} of the diverged."""

    def freeze(self, member: int) -> None:
        """Stop training ``member`` (zero its parameters and optimiser state)."""


@dataclass
class Learner:
    """A population's learner, as a family's ``build`` returns it: what the engine trains with."""

    networks: object  # the family's Networks: at least actor_net, critic_net (stacked) and sampler
    loss: torch.nn.Module
    optimisers: Optimisers
    memory: ReplayMemory
    phases: UpdatePhase
    transition_keys: tuple  # what the replay memory keeps of each step
    monte_carlo: bool  # the transitions carry Monte-Carlo returns (the paper's protocol)
    n_step: int = 1  # the memory keeps n-step transitions (collectors.returns.n_step_transitions)

    def member_weights(self, member: int) -> dict[str, dict[str, torch.Tensor]]:
        """Member ``member``'s trained weights, {"actor": ..., "critic": ...}, on the CPU."""
        critic = (self.phases.member_critic(member) if hasattr(self.phases, "member_critic")  # TorchRL's Q ensemble
                  else member_state_dict(self.networks.critic_net, member))
        actor = getattr(self.networks, "policy_net", self.networks.actor_net)  # as it acts (learners.td: normalised)
        return {"actor": member_state_dict(actor, member), "critic": critic}

    def state_parts(self) -> dict:
        """The stateful parts a checkpoint saves, by name."""
        parts = {"loss": self.loss, "actor_optim": self.optimisers.actor, "critic_optim": self.optimisers.critic,
                 "memory": self.memory}
        if hasattr(self.sampler, "state_dict"):
            parts["sampler"] = self.sampler
        return parts

    @property
    def sampler(self):
        """The acting policy, a ``learners.networks.BlockSampler``: ``[R, obs] -> [R, action]``."""
        return self.networks.sampler


def prioritised_minibatch(data: TensorDictBase, size: int, generators, sampler) -> tuple[TensorDictBase, torch.Tensor]:
    """``size`` transitions per member of ``data`` (``[R, n]``, the memory in slot order) drawn by
    the sampler's priorities, with their importance weights; and their slot indices ``[R, size]``."""
    index, weight = sampler.sample_members(data.batch_size[1], size, generators)
    device = data.device if data.device is not None else index.device
    index = index.to(device)
    rows = torch.arange(len(generators), device=device).unsqueeze(1)
    batch = data[rows, index]
    batch.set(PRIORITY_WEIGHT_KEY, weight.to(device, torch.float32))
    return batch, index


def objective(out: TensorDictBase, active: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """(the step's objective, the loss output's entries by name) from a loss's output: the sum over
    members of each active member's loss terms. Terms without a gradient (e.g. a zero-weight
    entropy bonus) are reported, not optimised."""
    entries = dict(out.items())
    losses = [value for key, value in entries.items() if key.startswith("loss_") and value.requires_grad]
    per_member = losses[0] if len(losses) == 1 else torch.stack(losses).sum(0)
    return (per_member * active).sum(), entries


def freeze_member(optimisers, member: int, others: list[tuple[torch.Tensor, int]] = ()) -> None:
    """Zero ``member``'s parameters and Adam moments in ``optimisers`` (and the (tensor, member
    dim) pairs of ``others``, e.g. target networks)."""
    with torch.no_grad():
        for optimiser in (optimisers.critic, optimisers.actor):
            for param, dim in zip(optimiser.params, optimiser.member_dims):
                param.select(dim, member).zero_()
            optimiser.zero_member(member)
        for tensor, dim in others:
            tensor.select(dim, member).zero_()


def _finite_per_member(params: list[torch.Tensor], member_dims: list[int] | None = None) -> torch.Tensor:
    member_dims = member_dims or [0] * len(params)
    members = params[0].shape[member_dims[0]]
    finite = torch.ones(members, dtype=torch.bool, device=params[0].device)
    for p, dim in zip(params, member_dims):
        finite &= torch.isfinite(p.detach()).movedim(dim, 0).reshape(members, -1).all(-1)
    return finite


def diverged_members(optimisers, totals: "MetricTotals", active: torch.Tensor) -> dict[int, str]:
    """{member: reason} for active members whose parameters or losses are NaN or infinite."""
    failed: dict[int, str] = {}
    for name, optimiser in (("critic", optimisers.critic), ("actor", optimisers.actor)):
        bad = ~_finite_per_member(optimiser.params, optimiser.member_dims)
        for member in bad.nonzero().flatten().tolist():
            failed.setdefault(member, f"the {name}'s parameters became NaN or infinite")
    for name, bad in totals.non_finite_losses().items():
        for member in bad.nonzero().flatten().tolist():
            failed.setdefault(member, f"{name} became NaN or infinite")
    return {m: reason for m, reason in failed.items() if active[m]}


class MetricTotals:
    """Per-step diagnostics of one episode's phases, per member (``critic/...``, ``actor/...``)."""

    def __init__(self):
        self.values: dict[str, list[torch.Tensor]] = defaultdict(list)

    def add(self, prefix: str, entries: dict[str, torch.Tensor]) -> None:
        for key, value in entries.items():
            self.values[f"{prefix}/{key}"].append(value.detach() if value.requires_grad else value)

    def non_finite_losses(self) -> dict[str, torch.Tensor]:
        """{loss name: [R] bool, True where a member's loss was NaN or infinite at some step}."""
        return {name: ~torch.stack(values).isfinite().all(0) for name, values in self.values.items()
                if name.split("/")[-1].startswith("loss_")}

    def means(self, members: int) -> list[dict[str, float]]:
        """One {name: mean over the episode's steps} per member."""
        # Each member's steps reduced on their own (a row at a time), so that a member's
        # means do not depend on how many members share the tensor.
        stacked = {name: [float(row.mean()) for row in torch.stack(values, -1).double().reshape(members, -1)]
                   for name, values in self.values.items()}
        return [{name: values[m] for name, values in stacked.items()} for m in range(members)]
