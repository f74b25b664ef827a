"""TD3's loss for a population (``MemberTD3Loss``: TorchRL's ``TD3Loss`` with the members' own target smoothing
noise) and its fused steps (``fused_td3_critic_losses``, ``fused_td3_actor_losses``), side by side; the fused steps
run only while ``learners.fast_paths`` finds the code they copy as it was checked."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import TD3Loss
from torchrl.objectives.utils import distance_loss

from losses.td import (check_no_masks, draws_masks, member_means, member_normal, owns_actor, stackable_critic,
                       stacked_values, td0_target)

SMOOTHING_KEY = "smoothing_noise"  # TD3: the clipped target smoothing noise under "next" (zeros at the root)


class MemberTD3Loss(TD3Loss):
    """``torchrl.objectives.TD3Loss`` with the members' own target smoothing noise (``draw``).

    TorchRL's ``value_loss`` adds ``clip(policy_noise * n, -c, c)`` to the target actor's action,
    with n from the global generator; here that term is zero (``policy_noise=0``) and the actor
    (``SmoothedActor``) adds the noise ``draw`` put under ``("next", SMOOTHING_KEY)``: the target
    is ``clip(mu'(s') + clip(policy_noise * n, -c, c), -1, 1)`` as TorchRL computes it. At the
    root the noise is zeros, so the actor loss sees ``mu(s)`` itself."""

    def __init__(self, actor, qvalue_networks, action_spec, *, policy_noise: float, noise_clip: float,
                 loss_function: str, generators: Sequence[torch.Generator] | None = None,
                 deactivate_vmap: bool = True):
        super().__init__(actor, qvalue_networks, action_spec=action_spec, num_qvalue_nets=len(qvalue_networks),
                         policy_noise=0.0, noise_clip=noise_clip, loss_function=loss_function,
                         reduction="none", deactivate_vmap=deactivate_vmap)
        self.smoothing, self.generators = policy_noise, list(generators) if generators is not None else None

    def draw(self, tensordict: TensorDictBase) -> None:
        """Each member's target smoothing noise for this minibatch into ``tensordict``."""
        action = tensordict.get("action")
        noise = member_normal(self.generators, action.shape[1:], action)
        tensordict.set(("next", SMOOTHING_KEY), (noise * self.smoothing).clamp(-self.noise_clip, self.noise_clip))
        tensordict.set(SMOOTHING_KEY, torch.zeros_like(action))


def fused_td3_available(loss, actor_net: nn.Module) -> bool:
    """Whether ``fused_td3_critic_losses`` and ``fused_td3_actor_losses`` compute ``loss``'s steps:
    TD3 eagerly, with stacked-MLP (plain or DroQ's) or residual Q-networks, and ``actor_net`` the
    loss's own (``make_actor_net``'s: a stacked MLP, then tanh)."""
    return (type(loss) is MemberTD3Loss and loss.deactivate_vmap and stackable_critic(loss)
            and owns_actor(loss, actor_net) and isinstance(actor_net, nn.Sequential) and len(actor_net) == 2
            and hasattr(actor_net[0], "forward_with"))


def _pairs(params: TensorDictBase, prefix: tuple, layers: int) -> list[tuple[torch.Tensor, torch.Tensor]]:
    return [(params.get((*prefix, str(i), "weight")), params.get((*prefix, str(i), "bias"))) for i in range(layers)]


def fused_td3_critic_losses(loss: MemberTD3Loss, actor_net: nn.Module,
                            batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """TD3's critic loss per member (``member_means`` of ``loss.value_loss(batch)[0]``) and the
    minibatch's priorities (the largest absolute TD error over the Q-networks), on plain tensors:
    the target actor's smoothed action ``clip(mu'(s') + noise, -1, 1)`` (the noise ``draw`` put under
    ``("next", SMOOTHING_KEY)``), the target ``r + gamma * min_j Q'_j(s', a')``, each Q-network's
    distance to it; TorchRL's ``TD3Loss.value_loss`` operation for operation (tested bit for bit)."""
    check_no_masks(batch)
    weights = loss._maybe_get_priority_weight(batch)
    following = batch.get("next")
    body = actor_net[0]
    with torch.no_grad():
        next_observation = following.get("observation")
        target_actor = _pairs(loss.target_actor_network_params, ("module", "net", "0", "layers"), len(body.layers))
        next_action = (torch.tanh(body.forward_with(next_observation, target_actor)) + following.get(SMOOTHING_KEY))
        next_action = next_action.clamp(loss.min_action, loss.max_action)
        next_values = stacked_values(loss, torch.cat([next_observation, next_action], -1),
                                      loss.target_qvalue_network_params).squeeze(-1)
    target = td0_target(loss, batch, next_values.min(0)[0].unsqueeze(-1))
    predicted = stacked_values(loss, torch.cat([batch.get("observation"), batch.get("action")], -1),
                                loss.qvalue_network_params).squeeze(-1)  # [Q, R, B]
    td_error = (predicted - target).pow(2)
    loss_qvalue = distance_loss(predicted, target.expand_as(predicted), loss_function=loss.loss_function).sum(0)
    if weights is not None:
        loss_qvalue = loss_qvalue * weights
    return member_means(loss_qvalue), td_error.detach().max(0).values.sqrt()


def fused_td3_actor_losses(loss: MemberTD3Loss, actor_net: nn.Module, batch: TensorDictBase) -> torch.Tensor:
    """TD3's actor loss per member (``member_means`` of ``loss.actor_loss(batch)[0]``): ``-Q_0(s, mu(s))``
    with the Q-networks detached, on plain tensors (tested bit for bit). TorchRL scores the action with
    every Q-network and keeps the first; only the first is computed here (the others' gradient is
    zero), unless the Q-networks draw dropout masks, whose draws must stay as TorchRL's.

    This copy runs on the fused path only. Off it (``compile=true``, a setting it does not compute) the actor's
    loss is TorchRL's ``TD3Loss.actor_loss``, which ``MemberTD3Loss`` inherits: to change TD3's actor loss in every
    mode, override ``actor_loss`` in ``MemberTD3Loss`` (the fused step then steps aside until mirrored and
    re-recorded, ``learners.fast_paths``). An edit made here alone is named by a run off the fused path."""
    check_no_masks(batch)
    weights = loss._maybe_get_priority_weight(batch)
    observation = batch.get("observation")
    action = actor_net(observation) + batch.get(SMOOTHING_KEY)  # zeros at the root, as SmoothedActor adds them
    params = loss.qvalue_network_params.detach()
    if not draws_masks(loss):
        params = params[:1]
    loss_actor = -stacked_values(loss, torch.cat([observation, action], -1), params)[0].squeeze(-1)
    if weights is not None:
        loss_actor = loss_actor * weights
    return member_means(loss_actor)


class SmoothedActor(nn.Module):
    """TD3's actor as ``MemberTD3Loss`` calls it: ``(observation, noise) -> mu(observation) + noise``."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, observation: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        return self.net(observation) + noise
