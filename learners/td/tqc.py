"""TQC: TorchRL's ``TQCLoss`` (``losses.tqc.MemberTQCLoss``): an ensemble of quantile critics whose pooled
target drops the highest quantiles, with SAC's learned temperature."""

from __future__ import annotations

from learners.options import ConfigError
from learners.registry import LearnerSpec
from learners.td import SACOptions, TQCOptions
from learners.td import sac


def _check(algo) -> None:
    given = (algo.td or {}).get("loss_function")
    if given is not None and given != "smooth_l1":
        raise ConfigError(f"algo {algo.name}: loss tqc trains its critics with the quantile Huber loss; set "
                          f"algo.td.loss_function: smooth_l1 (got {given})")


SPEC = LearnerSpec(name="tqc", title="TQC", family="td", module=__name__,
                   blocks={"sac": SACOptions, "tqc": TQCOptions}, check=_check,
                   critic=lambda algo: (algo.tqc.critics, algo.tqc.quantiles, True), gaussian_actor=True)
METRICS = sac.METRICS
actor, exploration_noise, prepare, losses, step = sac.actor, sac.exploration_noise, sac.prepare, sac.losses, sac.step


def critics(cfg, inputs, generators):
    from learners.td.learner import q_networks

    return q_networks(cfg, inputs, generators, count=cfg.algo.tqc.critics, outputs=cfg.algo.tqc.quantiles)


def loss(cfg, networks, generators):
    """Its critic loss is the quantile Huber loss (``algo.td.loss_function: smooth_l1``, checked)."""
    from learners.td.learner import entropy_loss_options
    from losses.tqc import MemberTQCLoss

    return MemberTQCLoss(networks.actor, networks.qvalues, top_quantiles_to_drop_per_net=cfg.algo.tqc.drop_per_critic,
                         **entropy_loss_options(cfg, networks, generators))


def fused_available(loss, actor_net) -> bool:
    from losses.tqc import fused_tqc_available

    return fused_tqc_available(loss, actor_net)


def fused_losses(loss, actor_net, batch):
    from losses.tqc import fused_tqc_losses

    return fused_tqc_losses(loss, actor_net, batch)
