"""CrossQ's loss for a population (``MemberCrossQLoss``: TorchRL's ``CrossQLoss``) and its fused steps
(``fused_crossq_critic_losses``, ``fused_crossq_actor_losses``), side by side; the fused steps run only while
``learners.fast_paths`` finds the code they copy as it was checked."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import CrossQLoss
from torchrl.objectives.utils import distance_loss

from losses.td import (ACTION_NOISE_KEY, MemberTemperature, check_no_masks, member_means, owns_actor, policy_sample,
                       stacked_values, td0_target)


class MemberCrossQLoss(MemberTemperature, CrossQLoss):
    """``torchrl.objectives.CrossQLoss`` (SAC without target networks: the critics, batch-normalised,
    score (s, a) and (s', a') in one forward pass, so that the normalisation sees both and the
    next state's value comes from the online critics) for stacked members: one temperature and
    the noise per member (``MemberTemperature``), and the joint pass concatenates along the
    minibatch dimension (1; TorchRL's concatenates along 0, which holds the members here)."""

    def qvalue_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """TorchRL's CrossQ critic loss per transition ``[R, B]``: each Q-network's distance to
        ``r + gamma * (min_j Q_j(s', a') - alpha * log pi(a'|s'))`` (a' drawn with the noise under
        ``("next", ACTION_NOISE_KEY)``, the target detached), summed over the Q-networks."""
        with (torch.no_grad(), set_exploration_type(ExplorationType.RANDOM),
              self.actor_network_params.to_module(self.actor_network, preserve_module_state=False)):
            following = tensordict.get("next").clone(False)
            next_action, next_log_prob = self.actor_network.get_dist(following).rsample_and_log_prob()
            following.set(self.tensor_keys.action, next_action)
        keys = self.qvalue_network.in_keys
        joint = torch.cat([tensordict.select(*keys, strict=False), following.select(*keys, strict=False)], dim=1)
        values = self._vmap_qnetworkN0(joint, self.qvalue_network_params).get(self.tensor_keys.state_action_value)
        current, following_values = values.split(tensordict.batch_size[1], dim=2)  # [Q-nets, R, B, 1] each
        next_value = (following_values.min(0)[0] - self._alpha.unsqueeze(-1) * next_log_prob.unsqueeze(-1)).detach()
        target = self.value_estimator.value_estimate(tensordict, next_value=next_value).squeeze(-1)
        predicted = current.squeeze(-1)
        loss = distance_loss(predicted, target.expand_as(predicted), loss_function=self.loss_function).sum(0)
        return loss, {"td_error": (predicted - target).abs().detach().max(0)[0]}

    def alpha_loss(self, log_prob: torch.Tensor, tensordict: TensorDictBase | None = None) -> torch.Tensor:
        return self._alpha_loss(log_prob)


def fused_crossq_available(loss, actor_net: nn.Module) -> bool:
    """Whether ``fused_crossq_critic_losses`` and ``fused_crossq_actor_losses`` compute ``loss``'s
    steps: CrossQ eagerly, its Q-networks batch-normalised stacked MLPs (``forward_stacked``), the
    actor network the loss's own."""
    return (type(loss) is MemberCrossQLoss and loss.deactivate_vmap
            and hasattr(getattr(loss.qvalue_network, "module", None), "forward_stacked")
            and owns_actor(loss, actor_net))


def fused_crossq_critic_losses(loss: "MemberCrossQLoss", actor_net: nn.Module,
                               batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """``MemberCrossQLoss.qvalue_loss`` per member (``member_means``) and its priorities, on plain
    tensors (tested bit for bit, running estimates included): the next action drawn with the noise
    under ``("next", ACTION_NOISE_KEY)``, (s, a) and (s', a') scored in one batch-normalised pass per
    Q-network, the target ``r + gamma * (min_j Q_j(s', a') - alpha * log pi(a'|s'))`` detached."""
    check_no_masks(batch)
    following = batch.get("next")
    with torch.no_grad():
        next_observation = following.get("observation")
        next_action, next_log_prob = policy_sample(actor_net, next_observation, following.get(ACTION_NOISE_KEY))
    joint = torch.cat([torch.cat([batch.get("observation"), batch.get("action")], -1),
                       torch.cat([next_observation, next_action], -1)], dim=1)
    values = stacked_values(loss, joint, loss.qvalue_network_params, loop_order=True, training=True)
    current, following_values = values.split(batch.batch_size[1], dim=2)  # [Q, R, B, 1] each
    next_value = (following_values.min(0)[0] - loss._alpha.unsqueeze(-1) * next_log_prob.unsqueeze(-1)).detach()
    target = td0_target(loss, batch, next_value)
    predicted = current.squeeze(-1)
    loss_qvalue = distance_loss(predicted, target.expand_as(predicted), loss_function=loss.loss_function).sum(0)
    return member_means(loss_qvalue), (predicted - target).abs().detach().max(0)[0]


def fused_crossq_actor_losses(loss: "MemberCrossQLoss", actor_net: nn.Module,
                              batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """TorchRL's ``CrossQLoss.actor_loss`` and ``MemberCrossQLoss.alpha_loss`` per member, on plain
    tensors (tested bit for bit): ``alpha * log pi(a|s) - min_j Q_j(s, a)`` with the Q-networks
    detached and in evaluation mode (their running estimates), and the temperature's loss."""
    check_no_masks(batch)
    observation = batch.get("observation")
    action, log_prob = policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
    values = stacked_values(loss, torch.cat([observation, action], -1), loss.qvalue_network_params.detach(),
                             loop_order=True, training=False)
    loss_actor = loss._alpha * log_prob - values.min(0)[0].squeeze(-1)
    return member_means(loss_actor), member_means(loss._alpha_loss(log_prob.detach()))
