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


class Diverged(RuntimeError):
    """A loss, gradient or parameter became NaN or infinite."""


class PhaseRunner:
    """Runs ``value_epochs`` critic steps then ``policy_epochs`` actor steps (Adam, one
    minibatch per member each, drawn with replacement from the member's data with its own
    generator), calling the loss's hooks where the protocol places them, and collects the
    loss's diagnostics per member."""

    def __init__(self, loss, optimisers, value_epochs: int, policy_epochs: int,
                 generators: list[torch.Generator]):
        self.loss = loss
        self.optimisers = optimisers
        self.value_epochs = value_epochs
        self.policy_epochs = policy_epochs
        self.generators = list(generators)
        self.critic_params = list(optimisers.critic.params)
        self.actor_params = list(optimisers.actor.params)
        self.active = torch.ones(len(self.generators), device=self.critic_params[0].device)  # 0: frozen

    def run(self, data: TensorDictBase, minibatch_size: int, totals: "MetricTotals") -> dict[int, str]:
        """One phase on ``data`` (``[R, n]``); returns {member: reason} for members that diverged."""
        loss = self.loss
        loss.before_critic_phase(data)
        for _ in range(self.value_epochs):
            out = loss.critic_loss(sample_minibatch(data, minibatch_size, self.generators))
            self._step(self.optimisers.critic, out, "critic", totals)
        loss.before_actor_phase(data)
        for _ in range(self.policy_epochs):
            out = loss.actor_loss(sample_minibatch(data, minibatch_size, self.generators))
            self._step(self.optimisers.actor, out, "actor", totals)
        loss.after_actor_phase()
        # Checked once per phase: a NaN or inf loss or gradient leaves non-finite parameters
        # (Adam propagates it), and one check per phase costs little per step.
        failed: dict[int, str] = {}
        for name, params in (("critic", self.critic_params), ("actor", self.actor_params)):
            bad = ~_finite_per_member(params)
            for member in bad.nonzero().flatten().tolist():
                failed.setdefault(member, f"the {name}'s parameters became NaN or infinite")
        for name, bad in totals.non_finite_losses().items():
            for member in bad.nonzero().flatten().tolist():
                failed.setdefault(member, f"{name} became NaN or infinite")
        return {m: reason for m, reason in failed.items() if self.active[m]}

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
        for optimiser in (self.optimisers.critic, self.optimisers.actor):
            for param in optimiser.params:
                param[member].zero_()
            optimiser.zero_member(member)


def _finite_per_member(params: list[torch.Tensor]) -> torch.Tensor:
    finite = torch.ones(params[0].shape[0], dtype=torch.bool, device=params[0].device)
    for p in params:
        finite &= torch.isfinite(p.detach()).reshape(p.shape[0], -1).all(-1)
    return finite


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
