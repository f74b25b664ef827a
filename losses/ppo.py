"""``LogClipPPOLoss``: PPO's clipped objective with the ratio in linear or log space."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule

from losses import functional as F
from losses.common import PhaseLoss, _members


class LogClipPPOLoss(PhaseLoss):
    """PPO with a Monte-Carlo V(s) critic; the probability ratio in linear or log space.

    Linear space: p = exp(logp - logp_old), clipped to [1 - eps, 1 + eps]. Log space:
    p = logp - logp_old, clipped to [log(1 - eps), log(1 + eps)]. The objective is
    mean(min(p A, clip(p) A)) + entropy_coeff * mean(entropy), maximised.

    Log-probabilities, ratios and entropies are per action dimension and averaged over batch
    and dimensions (``joint_log_prob=False``, the reference); ``joint_log_prob=True`` sums them
    over the dimensions first (then linear space matches torchrl's ``ClipPPOLoss``).

    Args:
        actor_network: a probabilistic actor whose ``get_dist`` gives the policy (e.g. a
            ``ProbabilisticActor`` over ``torch.distributions.Normal``).
        critic_network: writes V(s) to the ``value`` key.
        clip_epsilon: eps of the clip bounds.
        ratio_space: ``"linear"`` or ``"log"``.
        entropy_coeff: beta of the entropy bonus.
        joint_log_prob: sum log-probabilities and entropies over action dimensions.
        members: None, or the size R of a population (see ``losses.common.PhaseLoss``).

    Input keys: ``action``, ``value_target`` (the Monte-Carlo return G), and for the actor
    terms ``advantage`` and ``action_log_prob`` (added to a phase's data by
    ``before_critic_phase`` and ``before_actor_phase``).
    """

    @dataclass
    class _AcceptedKeys:
        action: str = "action"
        value_target: str = "value_target"
        advantage: str = "advantage"
        sample_log_prob: str = "action_log_prob"

    actor_network: ProbabilisticTensorDictSequential
    critic_network: TensorDictModule
    actor_metrics = ("loss_objective", "loss_entropy", "entropy", "clip_fraction", "approx_kl",
                     "ratio_mean", "advantage_mean")
    critic_attr = "critic_network"

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, critic_network: TensorDictModule,
                 *, clip_epsilon: float = 0.2, ratio_space: str = "linear", entropy_coeff: float = 0.02,
                 joint_log_prob: bool = False, members: int | None = None):
        super().__init__()
        F.clip_bounds(clip_epsilon, ratio_space)  # validates ratio_space
        self.members = _members(members)
        if not 0 < clip_epsilon < 1:
            raise ValueError(f"clip_epsilon must be in (0, 1), got {clip_epsilon!r}")
        self.actor_network = actor_network
        self.critic_network = critic_network
        self.clip_epsilon = float(clip_epsilon)
        self.ratio_space = ratio_space
        self.entropy_coeff = float(entropy_coeff)
        self.joint_log_prob = bool(joint_log_prob)

    # ------------------------------------------------------------------ phase preparation
    @torch.no_grad()
    def before_critic_phase(self, data: TensorDictBase) -> None:
        """A = G - V(s) for the whole phase data, under the critic before this phase's update."""
        keys = self.tensor_keys
        value = self._value(data)
        data.set(keys.advantage, data[keys.value_target] - value)

    @torch.no_grad()
    def before_actor_phase(self, data: TensorDictBase) -> None:
        """log pi_old(a | s) for the whole phase data, under the policy before this phase's update."""
        keys = self.tensor_keys
        data.set(keys.sample_log_prob, self._log_prob(self._policy(data), data[keys.action]))

    # ---------------------------------------------------------------------------- losses
    def actor_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        dist = self._policy(tensordict)
        log_prob = self._log_prob(dist, tensordict[keys.action])
        old_log_prob = tensordict[keys.sample_log_prob]
        if old_log_prob.shape != log_prob.shape:
            raise ValueError(f"{keys.sample_log_prob} has shape {tuple(old_log_prob.shape)} but the policy's "
                             f"log-probabilities have shape {tuple(log_prob.shape)} (joint_log_prob="
                             f"{self.joint_log_prob}); recompute it with before_actor_phase")
        advantage = tensordict[keys.advantage]
        ratio = F.ppo_ratio(log_prob, old_log_prob, self.ratio_space, self.members is not None)
        objective, clipped = F.clipped_surrogate(ratio, advantage, self.clip_epsilon, self.ratio_space)
        entropy, entropy_term = self._entropy(dist)
        return TensorDict({
            "loss_objective": -self._mean(objective),
            "loss_entropy": entropy_term,
            "entropy": entropy,
            "clip_fraction": self._mean(clipped.float()),
            "approx_kl": F.approx_kl(log_prob.detach(), old_log_prob, self.members is not None),
            "ratio_mean": self._mean(ratio.detach()),
            "advantage_mean": self._mean(advantage),
        })

    def _log_prob(self, dist: torch.distributions.Distribution, action: torch.Tensor) -> torch.Tensor:
        return F.per_dimension_or_joint(dist.log_prob(action), self.joint_log_prob)
