"""One training phase: a critic phase, then an actor phase, on one set of transitions."""

from __future__ import annotations

from collections import defaultdict

import torch
from tensordict import TensorDictBase

from collectors import sample_minibatch


class Diverged(RuntimeError):
    """A loss, gradient or parameter became NaN or infinite."""


class PhaseRunner:
    """Runs ``value_epochs`` critic steps then ``policy_epochs`` actor steps (Adam, one
    minibatch each, drawn with replacement from the phase's data), calling the loss's hooks
    where the protocol places them, and averages the loss's diagnostics over the steps."""

    def __init__(self, loss, optimisers, value_epochs: int, policy_epochs: int):
        self.loss = loss
        self.optimisers = optimisers
        self.value_epochs = value_epochs
        self.policy_epochs = policy_epochs
        self.critic_params = list(optimisers.critic.param_groups[0]["params"])
        self.actor_params = list(optimisers.actor.param_groups[0]["params"])

    def run(self, data: TensorDictBase, minibatch_size: int, totals: "MetricTotals") -> None:
        loss = self.loss
        loss.before_critic_phase(data)
        for _ in range(self.value_epochs):
            out = loss.critic_loss(sample_minibatch(data, minibatch_size))
            self._step(self.optimisers.critic, out, "critic", totals)
        loss.before_actor_phase(data)
        for _ in range(self.policy_epochs):
            out = loss.actor_loss(sample_minibatch(data, minibatch_size))
            self._step(self.optimisers.actor, out, "actor", totals)
        loss.after_actor_phase()
        # Checked once per phase: a NaN or inf loss or gradient leaves non-finite parameters
        # (Adam propagates it), and one check per phase costs nothing per step.
        for name, params in (("critic", self.critic_params), ("actor", self.actor_params)):
            if not all(bool(torch.isfinite(p).all()) for p in params):
                raise Diverged(f"the {name}'s parameters became NaN or infinite")
        totals.check_finite()

    @staticmethod
    def _step(optimiser, out: TensorDictBase, prefix: str, totals: "MetricTotals") -> None:
        entries = dict(out.items())
        # Terms without a gradient (e.g. a zero-weight entropy bonus) are reported, not optimised.
        losses = [value for key, value in entries.items() if key.startswith("loss_") and value.requires_grad]
        total = losses[0] if len(losses) == 1 else torch.stack(losses).sum()
        optimiser.zero_grad(set_to_none=True)
        total.backward()
        optimiser.step()
        totals.add(prefix, entries)


class MetricTotals:
    """Per-step diagnostics of one episode's phases, averaged (``critic/...`` and ``actor/...``)."""

    def __init__(self):
        self.values: dict[str, list[torch.Tensor]] = defaultdict(list)

    def add(self, prefix: str, entries: dict[str, torch.Tensor]) -> None:
        for key, value in entries.items():
            self.values[f"{prefix}/{key}"].append(value.detach() if value.requires_grad else value)

    def check_finite(self) -> None:
        for name, values in self.values.items():
            if name.split("/")[-1].startswith("loss_") and not bool(torch.stack(values).isfinite().all()):
                raise Diverged(f"{name} became NaN or infinite")

    def means(self) -> dict[str, float]:
        return {name: float(torch.stack(values).double().mean()) for name, values in self.values.items()}
