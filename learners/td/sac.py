"""SAC: TorchRL's ``SACLoss`` with one learned temperature per member (``losses.sac.MemberSACLoss``);
DroQ and BRO are its configurations (``conf/algo/droq.yaml``, ``bro.yaml``: their Q-networks).

The declaration (``SPEC``) is torch-free; the torch half (the functions below) imports torch when a
run builds the learner (``learners.td.learner``).
"""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, positive
from learners.registry import LearnerSpec


@dataclass(frozen=True)
class SACOptions:
    """``algo.sac``: TorchRL's ``SACLoss``'s temperature, and that of the losses built like it
    (``TQCLoss``, ``CrossQLoss``)."""

    alpha_init: float
    target_entropy: float | None  # None: TorchRL's "auto", minus the action dimension
    fixed_alpha: bool
    target_entropy_end: float | None = None  # None: the target stays; else it moves linearly from target_entropy
    #                                          at the first gradient step to this at the last episode

    def __post_init__(self) -> None:
        positive("algo.sac.alpha_init", self.alpha_init)
        for key in ("target_entropy", "target_entropy_end"):
            value = getattr(self, key)
            if value is not None and not -1e6 <= value <= 1e6:
                raise ConfigError(f"algo.sac.{key} must be within [-1e6, 1e6] nats (or null), got {value}")
        if self.target_entropy_end is not None and self.fixed_alpha:
            raise ConfigError("algo.sac.target_entropy_end moves the target the learned temperature follows; with "
                              "algo.sac.fixed_alpha: true there is none (set one of them back)")


SPEC = LearnerSpec(name="sac", title="SAC", family="td", module=__name__, blocks={"sac": SACOptions},
                   critic=lambda algo: (2, 1, True), gaussian_actor=True, past_critic=True,
                   pessimism=True)
METRICS = (("loss_qvalue",), ("loss_actor", "loss_alpha", "alpha"))  # metrics.csv's critic/ and actor/ columns


def actor(actor_net):
    from learners.td.learner import tanh_normal_actor

    return tanh_normal_actor(actor_net)


def critics(cfg, inputs, generators):
    from learners.td.learner import q_networks

    return q_networks(cfg, inputs, generators, count=2)


def exploration_noise(cfg) -> None:
    return None  # it samples its policy


def loss(cfg, networks, generators):
    from learners.td.learner import entropy_loss_options
    from losses.sac import MemberSACLoss

    return MemberSACLoss(networks.actor, networks.qvalues, loss_function=cfg.algo.td.loss_function,
                         pessimism=cfg.algo.td.pessimism, **entropy_loss_options(cfg, networks, generators))


def fused_available(loss, actor_net) -> bool:
    from losses.sac import fused_sac_available

    return fused_sac_available(loss, actor_net)


def fused_losses(loss, actor_net, batch):
    from losses.sac import fused_sac_losses

    return fused_sac_losses(loss, actor_net, batch)


def prepare(runner) -> None:
    from learners.compiling import compile_step

    runner.objective = compile_step(lambda batch: losses(runner, batch), runner.cfg.compile)


def losses(runner, batch):
    """Its three losses per member and the minibatch's priorities (TorchRL's loss writes them); the
    fused step where it computes them (``runner.fused``)."""
    from losses.common import PRIORITY_KEY
    from losses.td import member_means

    if runner.fused:
        return runner.steps_of.fused_losses(runner.loss, runner.actor_net, batch)
    out = runner.loss(batch)
    values = {key: member_means(out[key]) for key in ("loss_qvalue", "loss_actor", "loss_alpha")}
    return values, batch.get(PRIORITY_KEY)


def step(runner, batch, step, totals):
    """One step of all three losses together, then the target networks' soft update."""
    values, priority = runner.objective(batch)
    runner.minimise(sum(values.values()), runner.optimisers.critic, runner.optimisers.actor)
    runner.updater.step()
    totals.add("critic", {"loss_qvalue": values["loss_qvalue"]})
    totals.add("actor", {"loss_actor": values["loss_actor"], "loss_alpha": values["loss_alpha"],
                         "alpha": runner.loss.alpha})
    return priority
