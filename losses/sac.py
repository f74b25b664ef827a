"""SAC's loss for a population (``MemberSACLoss``: TorchRL's ``SACLoss`` with one entropy temperature per
member and the members' own noise) and its fused step (``fused_sac_losses``: the same numbers on plain tensors,
bit for bit), side by side. The fused step runs only while ``learners.fast_paths`` finds the code it copies as it
was checked."""

from __future__ import annotations

import contextlib

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import SACLoss
from torchrl.objectives.utils import distance_loss

from losses.td import (ACTION_NOISE_KEY, MemberTemperature, check_no_masks, member_means, owns_actor, policy_sample,
                       q_input, q_reduce, soft_td_target, stackable_critic, stacked_values)


class MemberSACLoss(MemberTemperature, SACLoss):
    """``torchrl.objectives.SACLoss`` with one entropy temperature per member and the members' own
    noise (``MemberTemperature``); everything else is TorchRL's. ``pessimism`` (``algo.td.pessimism``)
    replaces the minimum over the Q-networks in the target and the actor's objective by ``q_reduce``."""

    def __init__(self, *args, pessimism: float | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.pessimism = pessimism

    def _compute_target_v2(self, tensordict: TensorDictBase) -> torch.Tensor:
        with self._combined_values():
            return self._with_target_alpha(super()._compute_target_v2, tensordict)

    def actor_loss(self, tensordict: TensorDictBase):
        with self._combined_values():
            return super().actor_loss(tensordict)

    def values_of(self, outputs: torch.Tensor) -> torch.Tensor:
        """The Q-values ``[Q, ..., 1]`` the Q-networks' outputs stand for: the outputs themselves (a
        distributional critic's loss reads its logits' expected value: ``losses.simbav2``)."""
        return outputs

    @contextlib.contextmanager
    def _combined_values(self):
        """TorchRL's target and actor loss receive the Q-networks' values (``values_of``) combined by
        ``q_reduce`` (the same value in every network's entry, so the minimum they take is the combination)
        where ``pessimism`` is set or the outputs are not values; the critics' own loss, outside this, sees
        each network's outputs. Otherwise TorchRL's code runs as it is."""
        if self.pessimism is None and type(self).values_of is MemberSACLoss.values_of:
            yield
            return
        evaluate, key = self._vmap_qnetworkN0, self.tensor_keys.state_action_value

        def combined(tensordict, params):
            out = evaluate(tensordict, params)
            values = self.values_of(out.get(key))
            out.set(key, q_reduce(values, self.pessimism).unsqueeze(0).expand_as(values))
            return out

        self._vmap_qnetworkN0 = combined
        try:
            yield
        finally:
            self._vmap_qnetworkN0 = evaluate


def fused_sac_available(loss, actor_net: nn.Module) -> bool:
    """Whether ``fused_sac_losses`` computes ``loss``'s step: SAC (not TQC or CrossQ) eagerly, with
    Q-networks that are stacked MLPs (plain or DroQ's) or BRO's residual networks,
    and the actor network the loss's own."""
    return (type(loss) is MemberSACLoss and loss.deactivate_vmap and getattr(loss, "_version", 2) == 2
            and not loss.skip_done_states and stackable_critic(loss) and owns_actor(loss, actor_net))


def fused_sac_losses(loss: "MemberSACLoss", actor_net: nn.Module,
                     batch: TensorDictBase) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """``MemberSACLoss``'s three losses per member (``member_means`` of ``loss(batch)``) and the
    minibatch's priorities, computed on plain tensors: the same operations in the same order as
    TorchRL's ``SACLoss`` (v2: ``_compute_target_v2``, ``qvalue_v2_loss``, ``actor_loss``,
    ``_alpha_loss``, importance weights when the minibatch has them), so the same bits, forward
    and backward (tested), without its TensorDict and parameter-swapping work per call, which
    costs more than the arithmetic at these sizes. Where ``fused_sac_available`` holds."""
    check_no_masks(batch)
    keys = loss.tensor_keys
    weights = batch.get(keys.priority_weight, None) if loss.use_prioritized_weights in (True, "auto") else None
    observation = batch.get("observation")
    members = observation.shape[0]
    target, _ = soft_td_target(loss, actor_net, batch, loss.target_qvalue_network_params,
                                loss._alpha.reshape(members, 1, 1))
    predicted = stacked_values(loss, q_input(batch, observation, batch.get("action")),
                                loss.qvalue_network_params).squeeze(-1)
    td_error = abs(predicted - target)
    loss_qvalue = distance_loss(predicted, target.expand_as(predicted), loss_function=loss.loss_function).sum(0)
    action, log_prob = policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
    min_q = q_reduce(stacked_values(loss, q_input(batch, observation, action), loss.qvalue_network_params.detach()),
                     loss.pessimism).squeeze(-1)
    loss_actor = loss._alpha * log_prob - min_q
    loss_alpha = loss._alpha_loss(log_prob.detach())
    if weights is not None:
        loss_qvalue, loss_actor, loss_alpha = loss_qvalue * weights, loss_actor * weights, loss_alpha * weights
    losses = {"loss_qvalue": member_means(loss_qvalue), "loss_actor": member_means(loss_actor),
              "loss_alpha": member_means(loss_alpha)}
    return losses, td_error.detach().max(0)[0]
