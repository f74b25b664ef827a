"""TQC's loss for a population (``MemberTQCLoss``: TorchRL's ``TQCLoss``, its quantile Huber loss computed with
less memory traffic) and its fused step (``fused_tqc_losses``), side by side; the fused step runs only while
``learners.fast_paths`` finds the code it copies as it was checked."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import TQCLoss

from losses.td import (ACTION_NOISE_KEY, MemberTemperature, check_no_masks, member_means, owns_actor, policy_sample,
                       stackable_critic, stacked_values, td0_returns)


class _QuantileHuber(torch.autograd.Function):
    """TQC's critic loss per quantile set and its gradient, computed together (no autograd graph over the
    pairwise errors: the backward pass multiplies the saved gradient)."""

    @staticmethod
    def forward(ctx, quantiles: torch.Tensor, targets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n, m = quantiles.shape[-1], targets.shape[-1]
        fractions = ((torch.arange(n, device=quantiles.device, dtype=quantiles.dtype) + 0.5) / n).unsqueeze(-1)
        delta = targets.unsqueeze(-2) - quantiles.unsqueeze(-1)  # [..., n, m]
        # |tau_i - 1(delta < 0)|: tau_i where delta >= 0, 1 - tau_i where it is negative
        weight = torch.lt(delta, 0, out=torch.empty_like(delta)).mul_(1 - 2 * fractions).add_(fractions)
        td_error = delta.abs().sum((-1, -2)) / (n * m)
        clipped = delta.clamp(-1, 1)  # the Huber loss's derivative (threshold 1)
        huber = delta.sub_(clipped, alpha=0.5).mul_(clipped)  # 0.5 d^2 inside [-1, 1], |d| - 0.5 outside
        loss = huber.mul_(weight).sum((-1, -2)) / (n * m)
        ctx.save_for_backward(clipped.mul_(weight).sum(-1) / -(n * m))
        return loss, td_error

    @staticmethod
    def backward(ctx, grad_loss: torch.Tensor, grad_td_error: torch.Tensor) -> tuple[torch.Tensor, None]:
        (grad,) = ctx.saved_tensors
        return grad_loss.unsqueeze(-1) * grad, None


def quantile_huber_loss(quantiles: torch.Tensor, targets: torch.Tensor, *,
                        chunk: int = 2 ** 20) -> tuple[torch.Tensor, torch.Tensor]:
    """TQC's critic loss as ``TQCLoss`` defines it, for quantiles ``[..., B, n]`` (differentiable)
    and target atoms ``[..., B, m]`` (no gradient; broadcast against the quantiles' leading dims):
    ``mean_ij |tau_i - 1(d_ij < 0)| huber(d_ij)`` with ``d_ij = target_j - quantile_i``,
    ``tau_i = (i + 0.5) / n`` and Huber threshold 1, and the mean ``|d_ij|``; both ``[..., B]``.

    TorchRL's expression builds about twenty ``[..., B, n, m]`` tensors forward and backward;
    this computes the loss and its gradient together in about ten passes, over slices of the
    minibatch of at most ``chunk`` pairs (large tensors are fresh memory each step): 3x to 8x
    faster, the same values to float32 rounding (tested). Every transition's result is computed
    alone, so it does not depend on the slicing or on the other members."""
    targets = targets.detach()
    pairs = quantiles[..., 0, :].numel() * targets.shape[-1]  # per transition
    rows = max(1, chunk // max(pairs, 1))
    parts = [_QuantileHuber.apply(q, t) for q, t in zip(quantiles.split(rows, dim=-2), targets.split(rows, dim=-2))]
    return torch.cat([p[0] for p in parts], -1), torch.cat([p[1] for p in parts], -1)


class MemberTQCLoss(MemberTemperature, TQCLoss):
    """``torchrl.objectives.TQCLoss`` (truncated quantile critics: each Q-network outputs quantiles
    of the return; the target pools every target network's quantiles and drops the highest) with
    one entropy temperature per member and the members' own noise (``MemberTemperature``), and
    its critic loss through ``quantile_huber_loss`` (TorchRL's, computed with far less memory
    traffic: it was two thirds of a TQC step)."""

    def compute_target(self, tensordict: TensorDictBase) -> torch.Tensor:
        return self._with_target_alpha(super().compute_target, tensordict)

    def qvalue_v2_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """TorchRL's ``TQCLoss.qvalue_v2_loss``: each Q-network's quantile Huber loss against the
        truncated target atoms ``[R, B, m]``, summed over the Q-networks, weighted by priority
        when the minibatch carries weights; the |TD error| is the worst Q-network's mean."""
        weights = self._maybe_get_priority_weight(tensordict)
        targets = self.compute_target(tensordict)
        critic_input = tensordict.select(*self.qvalue_network.in_keys, strict=False)
        quantiles = self._vmap_qnetworkN0(critic_input, self.qvalue_network_params).get(
            self.tensor_keys.state_action_value)  # [Q-nets, R, B, n]
        loss, td_error = quantile_huber_loss(quantiles, targets.unsqueeze(0))
        return self._reduce_loss(loss.sum(0), tensordict=tensordict, weights=weights), {"td_error": td_error.max(0)[0]}


def fused_tqc_available(loss, actor_net: nn.Module) -> bool:
    """Whether ``fused_tqc_losses`` computes ``loss``'s step: TQC eagerly, with stacked-MLP (or
    residual) Q-networks and the actor network the loss's own."""
    return (type(loss) is MemberTQCLoss and loss.deactivate_vmap and getattr(loss, "_version", 2) == 2
            and not loss.skip_done_states and stackable_critic(loss) and owns_actor(loss, actor_net))


def fused_tqc_losses(loss: "MemberTQCLoss", actor_net: nn.Module,
                     batch: TensorDictBase) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """``MemberTQCLoss``'s three losses per member (``member_means`` of ``loss(batch)``) and the
    minibatch's priorities on plain tensors, TorchRL's ``TQCLoss`` operation for operation (tested bit
    for bit): the target pools every target Q-network's quantiles at ``(s', a')``, sorts them and drops
    the ``top_quantiles_to_drop_per_net * Q`` highest, ``r + gamma * (atom - alpha * log pi(a'|s'))`` per
    kept atom; each Q-network's quantile Huber loss against those atoms (``quantile_huber_loss``); the
    actor's ``alpha * log pi(a|s)`` minus the mean of every quantile of every (detached) Q-network."""
    check_no_masks(batch)
    weights = loss._maybe_get_priority_weight(batch)
    observation = batch.get("observation")
    members = observation.shape[0]
    with torch.no_grad():
        following = batch.get("next")
        next_observation = following.get("observation")
        next_action, next_log_prob = policy_sample(actor_net, next_observation, following.get(ACTION_NOISE_KEY))
        atoms = stacked_values(loss, torch.cat([next_observation, next_action], -1),
                                loss.target_qvalue_network_params)  # [Q, R, B, n]
        atoms = atoms.movedim(0, -2).flatten(-2)
        keep = atoms.shape[-1] - loss.top_quantiles_to_drop_per_net * loss.num_qvalue_nets
        atoms = torch.sort(atoms, dim=-1).values[..., :keep]
        next_value = atoms - loss._alpha.reshape(members, 1, 1) * next_log_prob.unsqueeze(-1)
        target = td0_returns(loss, batch, next_value)
    quantiles = stacked_values(loss, torch.cat([observation, batch.get("action")], -1), loss.qvalue_network_params)
    loss_qvalue, td_error = quantile_huber_loss(quantiles, target.unsqueeze(0))
    loss_qvalue = loss_qvalue.sum(0)
    action, log_prob = policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
    values = stacked_values(loss, torch.cat([observation, action], -1), loss.qvalue_network_params.detach(),
                             loop_order=True)
    loss_actor = loss._alpha * log_prob - values.mean(dim=(0, -1))
    loss_alpha = loss._alpha_loss(log_prob.detach())
    if weights is not None:
        loss_qvalue, loss_actor, loss_alpha = loss_qvalue * weights, loss_actor * weights, loss_alpha * weights
    losses = {"loss_qvalue": member_means(loss_qvalue), "loss_actor": member_means(loss_actor),
              "loss_alpha": member_means(loss_alpha)}
    return losses, td_error.max(0)[0]
