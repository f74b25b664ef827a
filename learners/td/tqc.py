"""TQC: TorchRL's ``TQCLoss`` (``losses.tqc.MemberTQCLoss``): an ensemble of quantile critics whose pooled
target drops the highest quantiles, with SAC's learned temperature."""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, at_least, capped
from learners.registry import LearnerSpec
from learners.td import sac
from learners.td.sac import SACOptions


@dataclass(frozen=True)
class TQCOptions:
    """``algo.tqc`` (TorchRL's ``TQCLoss``): the ensemble of quantile critics and the truncation."""

    critics: int = capped((1_000, "Q-networks"))  # each outputting `quantiles` quantiles of the return
    quantiles: int = capped((10_000, "quantiles per Q-network"))
    drop_per_critic: int  # the target drops the highest critics * drop_per_critic of the pooled quantiles

    def __post_init__(self) -> None:
        at_least("algo.tqc.critics", self.critics, 1)
        at_least("algo.tqc.quantiles", self.quantiles, 1)
        at_least("algo.tqc.drop_per_critic", self.drop_per_critic, 0)
        if self.drop_per_critic >= self.quantiles:
            raise ConfigError(f"algo.tqc.drop_per_critic must be below algo.tqc.quantiles ({self.quantiles}), "
                              f"got {self.drop_per_critic}: the target would keep no quantile")


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
