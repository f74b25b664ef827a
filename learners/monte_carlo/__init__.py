"""The paper's learners (``ppo``, ``spg``: their modules here, ``learners.registry``): a Monte-Carlo
critic, then per phase a critic phase and an actor phase on the member's transitions (the paper's
protocol).

This module is the family's torch-free half: the ``algo.*`` keys it requires, the option
dataclasses of its learners (validated before torch loads) and ``build``, which imports the torch
half (``learners.monte_carlo.learner``) on first use.
"""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, at_least, capped, choice

DESCRIPTION = "the paper's protocol (its learners: ppo, spg)"
OFF_POLICY = False  # trains on its own Monte-Carlo returns: any er mode
KEYS = ("value_epochs", "policy_epochs", "entropy_coeff", "joint_log_prob")  # algo.<key>, required
RATIO_SPACES = ("linear", "log")
CENTRES = ("mean", "action")


@dataclass(frozen=True)
class PPOOptions:
    """``algo.ppo`` (``losses.LogClipPPOLoss``)."""

    ratio_space: str
    clip_epsilon: float

    def __post_init__(self) -> None:
        choice("algo.ppo.ratio_space", self.ratio_space, RATIO_SPACES)
        if not 0 < self.clip_epsilon < 1:
            raise ConfigError(f"algo.ppo.clip_epsilon must be in (0, 1), got {self.clip_epsilon}")


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


BLOCKS = {}  # the family's own blocks (each learner declares its own: learners.registry)


def check(algo, learner) -> None:
    """Rules on the family's ``algo.*`` keys beyond their types."""
    for key in ("value_epochs", "policy_epochs", "entropy_coeff"):
        at_least(f"algo {algo.name}: {key}", getattr(algo, key), 0)


def build(cfg, env, generators, memory):
    """The members' networks, loss, optimisers and update phase: a ``learners.base.Learner``."""
    from learners.monte_carlo.learner import build

    return build(cfg, env, generators, memory)
