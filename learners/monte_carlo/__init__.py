"""The paper's learners (``ppo``, ``spg``: their modules here, ``learners.registry``): a Monte-Carlo
critic, then per phase a critic phase and an actor phase on the member's transitions (the paper's
protocol).

This module is the family's torch-free half: the ``algo.*`` keys it requires (each learner's own option
dataclass is in its module, validated before torch loads) and ``build``, which imports the torch half
(``learners.monte_carlo.learner``) on first use.
"""

from __future__ import annotations

from typing import Protocol

from learners.options import at_least

DESCRIPTION = "the paper's protocol"
OFF_POLICY = False  # trains on its own Monte-Carlo returns: any er mode
KEYS = ("value_epochs", "policy_epochs", "entropy_coeff", "joint_log_prob")  # algo.<key>, required
RATIO_SPACES = ("linear", "log")
CENTRES = ("mean", "action")


class LearnerModule(Protocol):
    """What a learner's module of the paper's family provides (``learners/monte_carlo/<name>.py``; the
    registry checks it when it finds the module, ``learners.registry.check_module``): its declaration and its
    loss. The phases, networks and critic are the family's (``SPEC.critic``'s third entry says whether the
    critic reads the action: Q(s, a) as SPG's, or V(s) as PPO's)."""

    SPEC: object  # its learners.registry.LearnerSpec

    def loss(self, cfg, networks, generators, common: dict):
        """Its loss module: a ``losses.common.PhaseLoss`` (critic loss, actor loss, the phase hooks) given the
        family's ``common`` settings (members, joint_log_prob, entropy_coeff)."""


ONE_OF: dict = {}
OPTIONAL: dict = {}

BLOCKS = {}  # the family's own blocks (each learner declares its own: learners.registry)


def check(algo, learner) -> None:
    """Rules on the family's ``algo.*`` keys beyond their types."""
    for key in ("value_epochs", "policy_epochs", "entropy_coeff"):
        at_least(f"algo {algo.name}: {key}", getattr(algo, key), 0)


def build(cfg, env, generators, memory):
    """The members' networks, loss, optimisers and update phase: a ``learners.base.Learner``."""
    from learners.monte_carlo.learner import build

    return build(cfg, env, generators, memory)
