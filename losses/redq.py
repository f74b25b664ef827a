"""REDQ's loss for a population (``MemberREDQLoss``: TorchRL's ``REDQLoss`` with one temperature, the noise and
its own subset of target networks per member); its step is the loss module's own ``population_losses``."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torch import nn
from torchrl.objectives import REDQLoss
from torchrl.objectives.utils import distance_loss

from losses.common import PRIORITY_WEIGHT_KEY
from losses.td import (ACTION_NOISE_KEY, MemberTemperature, check_no_masks, member_means, owns_actor, policy_sample,
                       q_input, soft_td_target, stackable_critic, stacked_values)


class MemberREDQLoss(MemberTemperature, REDQLoss):
    """``torchrl.objectives.REDQLoss`` (randomised ensembled double Q-learning: an ensemble of
    Q-networks, each regressed on a target that takes the minimum over a random subset of the
    target networks; the actor ascends the ensemble's mean) for stacked members: one temperature
    per member, bounded as TorchRL bounds it (``alpha``), the members' own noise, and each member's
    own random subset of target networks for each minibatch (``draw``; TorchRL draws one subset
    from torch's global generator). A population's step is ``population_losses`` (TorchRL's ``forward``
    takes one subset for the whole minibatch)."""

    def __init__(self, *args, subset: int, **kwargs):
        super().__init__(*args, sub_sample_len=subset, **kwargs)  # as sub_sample_len (algo.redq checks it)
        self.subsets: torch.Tensor | None = None  # [subset, R]: each member's target networks, this minibatch
        self.target_entropy  # TorchRL registers it as a buffer on first use: from the start, so checkpoints load

    def draw(self, tensordict: TensorDictBase) -> None:
        """Each member's noise (``MemberTemperature.draw``), then its subset of target networks: the
        first ``sub_sample_len`` of a random permutation, in increasing order (as TorchRL draws its one)."""
        super().draw(tensordict)
        self.subsets = torch.stack([torch.randperm(self.num_qvalue_nets, generator=g, device=g.device)[:self.sub_sample_len]
                                    .sort()[0] for g in self.generators], 1)

    @property
    def _alpha(self) -> torch.Tensor:
        """Each member's temperature as TorchRL's REDQ uses it (bounded, not trained through), ``[R]``."""
        with torch.no_grad():
            return self.log_alpha.clamp(self.min_log_alpha, self.max_log_alpha).exp()

    @property
    def alpha(self) -> torch.Tensor:
        return self._alpha

    def forward(self, tensordict: TensorDictBase):
        raise NotImplementedError("a population's REDQ losses are MemberREDQLoss.population_losses (TorchRL's "
                                  "forward draws one subset of target networks for all members)")

    def population_losses(self, actor_net: nn.Module, batch: TensorDictBase,
                          actor: bool = True) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """REDQ's losses per member and the minibatch's priorities, as TorchRL's ``REDQLoss.forward``
        computes them (tested) for each member with its own subset of target networks
        (``self.subsets``, drawn by ``self.draw``) and its own temperature:

        - ``loss_qvalue``: the mean over the ensemble of each Q-network's distance to the target
          ``r + gamma * (min_{j in subset} Q'_j(s', a') - alpha * log pi(a'|s'))``;
        - ``loss_actor`` (when ``actor``): the ensemble's mean of ``alpha * log pi(a|s) - Q_i(s, a)``
          (the Q-networks detached);
        - ``loss_alpha`` (when ``actor``): ``-alpha * (log pi + target entropy)`` over the actor's and
          the target's draws, with TorchRL's bounds on alpha (its gradient passes the bounds).

        Two departures from TorchRL's, both for prioritised replay only: the losses are weighted by the
        minibatch's importance weights (as ``SACLoss`` weights them; ``REDQLoss`` ignores them), and the
        priority is the largest absolute TD error over the ensemble (SAC's; ``REDQLoss`` writes squared
        errors)."""
        check_no_masks(batch)
        weights = batch.get(PRIORITY_WEIGHT_KEY, None)
        observation = batch.get("observation")
        members = observation.shape[0]
        if self.subsets is None or self.subsets.shape[1] != members:
            raise RuntimeError("population_losses needs each member's subset of target networks: "
                               "call draw(batch) first")
        rows = torch.arange(members, device=self.subsets.device)
        chosen = self.target_qvalue_network_params.apply(lambda value: value[self.subsets, rows],  # [subset, R, ...]
                                                         batch_size=[self.subsets.shape[0]])
        alpha = self._alpha.reshape(members, 1)
        target, next_log_prob = soft_td_target(self, actor_net, batch, chosen, alpha.unsqueeze(-1))
        predicted = stacked_values(self, q_input(batch, observation, batch.get("action")),
                                    self.qvalue_network_params).squeeze(-1)  # [Q, R, B]
        td_error = abs(predicted - target)
        loss_qvalue = distance_loss(predicted, target.expand_as(predicted), loss_function=self.loss_function).mean(0)
        losses = {"loss_qvalue": loss_qvalue}
        if actor:
            action, log_prob = policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
            values = stacked_values(self, q_input(batch, observation, action),
                                     self.qvalue_network_params.detach()).squeeze(-1)
            losses["loss_actor"] = -(values - alpha * log_prob).mean(0)
            log_alpha = self.log_alpha.reshape(members, 1)
            bounded = log_alpha - log_alpha.detach() + log_alpha.detach().clamp(self.min_log_alpha, self.max_log_alpha)
            entropy_gap = torch.stack([log_prob.detach(), next_log_prob]) + self.target_entropy  # [2, R, B]
            # -alpha x gap per member: alpha's gradient then sums each member's own [2, B] (a broadcast over
            # [2, R, B] would sum over dims 0 and 2 in an order that depends on R: a member would not be its solo run)
            scale = -bounded.exp()
            terms = [scale[r] * entropy_gap[:, r].contiguous() for r in range(members)]
            losses["loss_alpha"] = torch.stack(terms, 1).mean(0)
        if weights is not None:
            losses = {key: value * weights for key, value in losses.items()}
        return {key: member_means(value) for key, value in losses.items()}, td_error.detach().max(0)[0]


def redq_available(loss, actor_net: nn.Module) -> bool:
    """Whether ``MemberREDQLoss.population_losses`` computes ``loss``'s step (plain or residual Q-networks,
    eager, the loss's own actor network)."""
    return isinstance(loss, MemberREDQLoss) and loss.deactivate_vmap and stackable_critic(loss) \
        and owns_actor(loss, actor_net)
