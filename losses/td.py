"""TorchRL's off-policy losses (``SACLoss``, ``TD3Loss``) for a population of stacked members.

The losses are TorchRL's own; what a population needs on top is small:

- Every tensor has the members first (``[R, B, ...]``) and the networks are stacked
  (``learners.networks``), so TorchRL's ensemble of Q-networks has parameters of shape
  ``[2, R, ...]`` (Q-network, member, ...). Both Q-networks are passed as modules (a list), so
  their initial weights are ours (each member's from its own generator), not TorchRL's
  resampling of one network's weights over all members' range.
- ``reduction="none"``: the losses come back per transition (``[R, B]``); ``member_means``
  turns them into one value per member, whose sum is minimised (each member's gradient its own).
- SAC's entropy temperature: one per member (``MemberSACLoss``), since a shared temperature
  would couple the members.

What stays shared: the Gaussian noise TorchRL's losses draw inside (SAC's reparameterised
actions, TD3's target smoothing) comes from torch's global generator, so a member's numbers
depend on which members it is trained with (they are reproducible for the same population).
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.objectives import SACLoss, TD3Loss

from losses.common import PRIORITY_KEY  # noqa: F401  (TorchRL's SAC writes each transition's |TD error| there)



class MemberSACLoss(SACLoss):
    """``torchrl.objectives.SACLoss`` with one entropy temperature per member (``log_alpha`` of
    shape ``[R]``); everything else is TorchRL's."""

    def __init__(self, *args, members: int, **kwargs):
        super().__init__(*args, reduction="none", scalar_output_mode="exclude", **kwargs)
        self.members = members
        log_alpha = torch.full((members,), math.log(float(self.alpha_init)), device=self.alpha_init.device)
        del self.log_alpha
        if self.fixed_alpha:
            self.register_buffer("log_alpha", log_alpha)
        else:
            self.log_alpha = torch.nn.Parameter(log_alpha)
        self._alpha_shape = (members, 1)  # broadcasts against [R, B] log-probabilities

    @property
    def _alpha(self) -> torch.Tensor:
        if self.min_log_alpha is not None or self.max_log_alpha is not None:
            self.log_alpha.data.clamp_(self.min_log_alpha, self.max_log_alpha)
        with torch.no_grad():
            return self.log_alpha.exp().reshape(self._alpha_shape)

    def _compute_target_v2(self, tensordict: TensorDictBase) -> torch.Tensor:
        # There TorchRL scales [Q-nets, R, B, 1] values by alpha: one more trailing dimension.
        self._alpha_shape = (self.members, 1, 1)
        try:
            return super()._compute_target_v2(tensordict)
        finally:
            self._alpha_shape = (self.members, 1)

    def _alpha_loss(self, log_prob: torch.Tensor) -> torch.Tensor:
        if self.target_entropy is None:
            return torch.zeros_like(log_prob)
        return -self.log_alpha.unsqueeze(-1) * (log_prob + self.target_entropy)

    @property
    def alpha(self) -> torch.Tensor:
        """Each member's temperature, ``[R]``."""
        return self.log_alpha.detach().exp()


def member_means(values: torch.Tensor) -> torch.Tensor:
    """``[R, B]`` per-transition values -> ``[R]``, one mean per member."""
    return values.reshape(values.shape[0], -1).mean(-1)


def make_td3_loss(actor, qvalue_networks, action_spec, *, policy_noise: float, noise_clip: float,
                  loss_function: str, deactivate_vmap: bool = True) -> TD3Loss:
    """TorchRL's ``TD3Loss`` with per-transition losses (``reduction="none"``). ``deactivate_vmap``:
    loop over the Q-networks (faster eagerly; ``torch.compile`` recompiles it on every call)."""
    return TD3Loss(actor, qvalue_networks, action_spec=action_spec, num_qvalue_nets=len(qvalue_networks),
                   policy_noise=policy_noise, noise_clip=noise_clip, loss_function=loss_function,
                   reduction="none", deactivate_vmap=deactivate_vmap)
