"""SPG as the paper trains it (``losses.SPGLoss``): a Monte-Carlo critic Q(s, a), then the actor moved towards
the best of sampled actions (SPG-p: prioritised; ``spg_multi``: several epochs)."""

from __future__ import annotations

from learners.monte_carlo import SPGOptions
from learners.registry import LearnerSpec

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
