"""One training phase of a population: a critic phase, then an actor phase, on each member's
own transitions.

Every loss term is one value per member (``[R]``); a step minimises their sum, so each
member's gradient is its own, and Adam (element-wise) updates each member as if it were
alone. A member whose loss or parameters become NaN or infinite is reported after the phase;
the caller freezes it (``freeze``): its parameters and optimiser state are zeroed and its loss
terms masked out, so it stays finite and fixed while the others go on.
"""

from __future__ import annotations

from collections import defaultdict

import torch
from tensordict import TensorDictBase

from collectors import sample_minibatch
from losses.common import PRIORITY_KEY, PRIORITY_WEIGHT_KEY


class Diverged(RuntimeError):
    """A loss, gradient or parameter became NaN or infinite."""


class PhaseRunner:
    """Runs ``value_epochs`` critic steps then ``policy_epochs`` actor steps (Adam, one
    minibatch per member each, drawn with replacement from the member's data with its own
    generator), calling the loss's hooks where the protocol places them, and collects the
    loss's diagnostics per member."""

    def __init__(self, loss, optimisers, value_epochs: int, policy_epochs: int,
                 generators: list[torch.Generator], sampler=None):
        """``sampler``: a ``collectors.prioritised.ProportionalSampler`` holding the replay
        memory's priorities (prioritised replay: every minibatch is drawn by priority, the critic's
        loss weighted by importance and its errors |G - critic| become the new priorities), or None."""
        self.loss = loss
        self.optimisers = optimisers
        self.value_epochs = value_epochs
        self.policy_epochs = policy_epochs
        self.generators = list(generators)
        self.sampler = sampler
        self.active = torch.ones(len(self.generators), device=optimisers.critic.params[0].device)  # 0: frozen
        self.critic_metrics, self.actor_metrics = loss.critic_metrics, loss.actor_metrics

    def run(self, data: TensorDictBase, minibatch_size: int, totals: "MetricTotals", episode: int = 0) -> dict[int, str]:
        """One phase on ``data`` (``[R, n]``) before or after episode ``episode`` (unused: every phase
        is alike); returns {member: reason} for members that diverged."""
        loss = self.loss
        loss.before_critic_phase(data)
        for _ in range(self.value_epochs):
            batch, index = self._minibatch(data, minibatch_size)
            out = loss.critic_loss(batch)
            if index is not None:
                self.sampler.update_priority(index.cpu(), out.pop(PRIORITY_KEY).cpu())
            self._step(self.optimisers.critic, out, "critic", totals)
        loss.before_actor_phase(data)
        for _ in range(self.policy_epochs):
            out = loss.actor_loss(self._minibatch(data, minibatch_size)[0])
            self._step(self.optimisers.actor, out, "actor", totals)
        loss.after_actor_phase()
        # Checked once per phase: a NaN or inf loss or gradient leaves non-finite parameters
        # (Adam propagates it), and one check per phase costs little per step.
        return diverged_members(self.optimisers, totals, self.active)

    def _minibatch(self, data: TensorDictBase, size: int) -> tuple[TensorDictBase, torch.Tensor | None]:
        """A minibatch per member, uniform (and no index) or by priority (with its slot indices)."""
        if self.sampler is None:
            return sample_minibatch(data, size, self.generators), None
        return prioritised_minibatch(data, size, self.generators, self.sampler)

    def _step(self, optimiser, out: TensorDictBase, prefix: str, totals: "MetricTotals") -> None:
        entries = dict(out.items())
        # Terms without a gradient (e.g. a zero-weight entropy bonus) are reported, not optimised.
        losses = [value for key, value in entries.items() if key.startswith("loss_") and value.requires_grad]
        per_member = losses[0] if len(losses) == 1 else torch.stack(losses).sum(0)
        optimiser.zero_grad(set_to_none=True)
        (per_member * self.active).sum().backward()
        optimiser.step()
        totals.add(prefix, entries)

    @torch.no_grad()
    def freeze(self, member: int) -> None:
        """Stop training ``member``: zero its parameters and Adam moments, mask its loss terms.

        With zero gradient, zero moments and zero weights, Adam leaves it at zero; its
        networks stay finite (its car keeps driving, unrecorded) and cost the others nothing.
        """
        self.active[member] = 0.0
        freeze_member(self.optimisers, member)


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
