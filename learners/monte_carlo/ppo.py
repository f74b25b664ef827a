"""PPO as the paper trains it (``losses.LogClipPPOLoss``): a Monte-Carlo critic V(s), then the clipped surrogate,
its probability ratio in linear space (``ppo``) or in log space (``ppo_log``: ``algo.ppo.ratio_space: log``)."""

from __future__ import annotations

from dataclasses import dataclass

from learners.monte_carlo import RATIO_SPACES
from learners.options import ConfigError, choice
from learners.registry import LearnerSpec


@dataclass(frozen=True)
class PPOOptions:
    """``algo.ppo`` (``losses.LogClipPPOLoss``)."""

    ratio_space: str
    clip_epsilon: float

    def __post_init__(self) -> None:
        choice("algo.ppo.ratio_space", self.ratio_space, RATIO_SPACES)
        if not 0 < self.clip_epsilon < 1:
            raise ConfigError(f"algo.ppo.clip_epsilon must be in (0, 1), got {self.clip_epsilon}")


SPEC = LearnerSpec(name="ppo", title="PPO", family="monte_carlo", module=__name__, blocks={"ppo": PPOOptions},
                   critic=lambda algo: (1, 1, False))  # V(s)


def loss(cfg, networks, generators, common: dict):
    from losses import LogClipPPOLoss

    ppo = cfg.algo.ppo
    return LogClipPPOLoss(networks.actor, networks.critic, clip_epsilon=ppo.clip_epsilon, ratio_space=ppo.ratio_space,
                          **common)
