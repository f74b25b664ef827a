"""PPO as the paper trains it (``losses.LogClipPPOLoss``): a Monte-Carlo critic V(s), then the clipped surrogate,
its probability ratio in linear space (``ppo``) or in log space (``ppo_log``: ``algo.ppo.ratio_space: log``)."""

from __future__ import annotations

from learners.monte_carlo import PPOOptions
from learners.registry import LearnerSpec

SPEC = LearnerSpec(name="ppo", title="PPO", family="monte_carlo", module=__name__, blocks={"ppo": PPOOptions},
                   critic=lambda algo: (1, 1, False))  # V(s)


def loss(cfg, networks, generators, common: dict):
    from losses import LogClipPPOLoss

    ppo = cfg.algo.ppo
    return LogClipPPOLoss(networks.actor, networks.critic, clip_epsilon=ppo.clip_epsilon, ratio_space=ppo.ratio_space,
                          **common)
