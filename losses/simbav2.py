"""SAC with categorical critics and scaled rewards (SimbaV2's loss; Lee et al., 2025), for a population.

``DistributionalSACLoss`` is ``losses.sac.MemberSACLoss`` (TorchRL's ``SACLoss``: its actor and temperature
losses, one temperature per member, the members' own noise) whose Q-networks output the logits of a
categorical distribution of the return over a fixed, evenly spaced support ``[v_min, v_max]`` (``bins``
points). The critic's loss is the cross-entropy to the target distribution: the target network's
distribution at ``(s', a')``, ``a' ~ pi(.|s')``, its support moved to ``r / scale + gamma * (z - alpha *
log pi(a'|s'))`` (``gamma`` 0 where the episode terminated) and projected back onto the support
(``categorical_projection``); with more than one Q-network, the target is the distribution of the one whose
expected value at ``(s', a')`` is lowest (clipped double Q, as SimbaV2 does for tasks that end). The actor
ascends the expected value (the lowest over the Q-networks, or ``algo.td.pessimism``'s combination).

``scale`` is each member's reward scale (``reward_scale``, ``[R]``), set by the learner before its steps
(``learners.td.simbav2``): rewards are divided by it so that returns fit the support.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives.sac import compute_rsample_log_prob

from losses.sac import MemberSACLoss


def categorical_projection(probs: torch.Tensor, atoms: torch.Tensor, v_min: float, v_max: float) -> torch.Tensor:
    """The distribution of mass ``probs`` ``[..., K]`` at the points ``atoms`` ``[..., K]`` on the support of K
    evenly spaced points from ``v_min`` to ``v_max``: each atom, clipped to that range, splits its mass between
    the two support points around it in proportion to its closeness to each (an atom on a point keeps its mass
    there)."""
    points = probs.shape[-1]
    position = ((atoms.clamp(v_min, v_max) - v_min) / ((v_max - v_min) / (points - 1))).clamp(0, points - 1)
    lower, upper = position.floor(), position.ceil()
    to_lower = probs * (upper + (lower == upper).to(probs.dtype) - position)
    to_upper = probs * (position - lower)
    out = torch.zeros_like(probs)
    out.scatter_add_(-1, lower.long(), to_lower)
    return out.scatter_add_(-1, upper.long(), to_upper)


class DistributionalSACLoss(MemberSACLoss):
    def __init__(self, *args, support: tuple[float, float, int], **kwargs):
        super().__init__(*args, **kwargs)
        v_min, v_max, bins = support
        self.v_min, self.v_max = float(v_min), float(v_max)
        self.register_buffer("support", torch.linspace(v_min, v_max, bins))
        self.register_buffer("reward_scale", torch.ones(self.members))

    def values_of(self, outputs: torch.Tensor) -> torch.Tensor:
        """The expected return of each distribution: ``[..., bins]`` logits -> ``[..., 1]``."""
        return (outputs.softmax(-1) * self.support).sum(-1, keepdim=True)

    @torch.no_grad()
    def target_distribution(self, tensordict: TensorDictBase) -> torch.Tensor:
        """The projected target distribution ``[R, B, bins]`` (the module's docstring)."""
        keys, following = self.tensor_keys, tensordict.get("next").copy()
        with set_exploration_type(ExplorationType.RANDOM), self.actor_network_params.to_module(
                self.actor_network, preserve_module_state=False):
            next_action, next_log_prob = compute_rsample_log_prob(self.actor_network.get_dist(following))
        following.set(keys.action, next_action)
        logits = self._vmap_qnetworkN0(following, self.target_qvalue_network_params).get(keys.state_action_value)
        probs = logits.softmax(-1)  # [Q, R, B, bins]
        if probs.shape[0] > 1:
            lowest = (probs * self.support).sum(-1).argmin(0)  # [R, B]
            probs = probs.gather(0, lowest[None, ..., None].expand(1, *probs.shape[1:]))
        probs = probs[0]
        members = probs.shape[0]
        reward = following.get(keys.reward) / self.reward_scale.view(members, 1, 1)
        gamma = self.value_estimator.gamma.to(reward.device)
        steps = tensordict.get(self.value_estimator.tensor_keys.steps_to_next_obs, None)
        if steps is not None:
            gamma = gamma ** steps.view_as(reward)
        going = (~following.get(keys.terminated)).to(reward.dtype)
        atoms = reward + gamma * going * (self.support - (self._alpha * next_log_prob).unsqueeze(-1))
        return categorical_projection(probs, atoms, self.v_min, self.v_max)

    def qvalue_v2_loss(self, tensordict: TensorDictBase):
        weights = self._maybe_get_priority_weight(tensordict)
        target = self.target_distribution(tensordict)
        key = self.tensor_keys.state_action_value
        logits = self._vmap_qnetworkN0(tensordict.select(*self.qvalue_network.in_keys, strict=False),
                                       self.qvalue_network_params).get(key)  # [Q, R, B, bins]
        loss = -(target * logits.log_softmax(-1)).sum(-1).sum(0)
        td_error = (self.values_of(logits).squeeze(-1) - (target * self.support).sum(-1)).abs()
        loss = self._reduce_loss(loss, tensordict=tensordict, weights=weights)
        return loss, {"td_error": td_error.detach().max(0)[0]}
