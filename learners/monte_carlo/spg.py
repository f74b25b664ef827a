"""SPG as the paper trains it (``losses.SPGLoss``): a Monte-Carlo critic Q(s, a), then the actor moved towards
the best of sampled actions (SPG-p: prioritised; ``spg_multi``: several epochs)."""

from __future__ import annotations

from dataclasses import dataclass

from learners.monte_carlo import CENTRES
from learners.options import ConfigError, at_least, capped, choice
from learners.registry import LearnerSpec


@dataclass(frozen=True)
class SPGOptions:
    """``algo.spg`` (``losses.SPGLoss``)."""

    prioritised: bool
    num_samples: int = capped((100_000, "sampled actions per state"))
    temperature: float
    temperature_decay: float
    sample_around: str
    baseline: str

    def __post_init__(self) -> None:
        choice("algo.spg.sample_around", self.sample_around, CENTRES)
        choice("algo.spg.baseline", self.baseline, CENTRES)
        at_least("algo.spg.num_samples", self.num_samples, 0)
        at_least("algo.spg.temperature", self.temperature, 0)
        if not 0 <= self.temperature_decay < 1:
            raise ConfigError(f"algo.spg.temperature_decay must be in [0, 1), got {self.temperature_decay}")


SPEC = LearnerSpec(name="spg", title="SPG", family="monte_carlo", module=__name__, blocks={"spg": SPGOptions},
                   critic=lambda algo: (1, 1, True),  # Q(s, a)
                   rows=lambda algo, minibatch: minibatch * max(1, algo.spg.num_samples))  # it scores sampled actions


def loss(cfg, networks, generators, common: dict):
    from losses import SPGLoss

    spg = cfg.algo.spg
    loss = SPGLoss(networks.actor, networks.critic, num_samples=spg.num_samples, temperature=spg.temperature,
                   temperature_decay=spg.temperature_decay, prioritised=spg.prioritised,
                   sample_around=spg.sample_around, baseline=spg.baseline, **common)
    loss.set_generators(generators)
    return loss
