"""Normalized Advantage Functions (Gu, Lillicrap, Sutskever and Levine, 2016) as a TorchRL loss.

NAF is Q-learning with a Q-function whose maximum over actions is known in closed form:

    Q(s, a) = V(s) + A(s, a),   A(s, a) = -1/2 (a - mu(s))^T P(s) (a - mu(s)),   P = L L^T,

with L(s) lower-triangular and its diagonal exponentiated (so P is positive definite and A <= 0,
zero at a = mu(s)). The greedy action is mu(s); here mu is bounded to the action range by a tanh,
as the other learners' actors are. The Q-function is fitted to one-step TD targets from a target
network's value, y = r + gamma * V'(s') where not terminated, and every parameter (mu's, V's and
L's) descends the same squared (or l1, smooth l1) error.

Networks: ``actor_network`` maps the observation to mu (the acting policy, saved and evaluated
as TD3's actor is); ``value_network`` maps it to ``1 + D (D + 1) / 2`` numbers: V, then L's
entries row by row (``torch.tril_indices``' order). Populations: every tensor has the members
first (``[R, B, ...]``) and the losses come back per transition (``[R, B]``), as the project's
other off-policy losses (``losses.td``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators, distance_loss
from torchrl.objectives.value import TD0Estimator
from torchrl.objectives.value.functional import td0_return_estimate

from losses.common import PRIORITY_KEY, PRIORITY_WEIGHT_KEY, module_call


def lower_entries(action_dim: int) -> int:
    """How many numbers parametrise L for ``action_dim`` actions: ``D (D + 1) / 2``."""
    return action_dim * (action_dim + 1) // 2


def naf_lower(entries: torch.Tensor, action_dim: int) -> torch.Tensor:
    """L ``[..., D, D]`` from its ``D (D + 1) / 2`` entries ``[..., E]`` (row by row, as
    ``torch.tril_indices`` lists them): lower-triangular, its diagonal ``exp`` of the entries there."""
    rows, cols = torch.tril_indices(action_dim, action_dim, device=entries.device)
    values = torch.where(rows == cols, entries.exp(), entries)
    flat = entries.new_zeros(*entries.shape[:-1], action_dim * action_dim)
    return flat.index_copy(-1, rows * action_dim + cols, values).unflatten(-1, (action_dim, action_dim))


def naf_advantage(entries: torch.Tensor, mu: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """``A(s, a) = -1/2 (a - mu)^T L L^T (a - mu) = -1/2 |L^T (a - mu)|^2`` ``[...]`` from L's entries
    ``[..., E]``, mu and the action ``[..., D]``."""
    lower = naf_lower(entries, mu.shape[-1])
    projected = (lower * (action - mu).unsqueeze(-1)).sum(-2)  # L^T (a - mu): sum over L's rows
    return -0.5 * projected.square().sum(-1)


def naf_precision(entries: torch.Tensor, action_dim: int) -> torch.Tensor:
    """P = L L^T ``[..., D, D]`` (the advantage's curvature), for diagnostics and tests."""
    lower = naf_lower(entries, action_dim)
    return lower @ lower.transpose(-1, -2)


class NAFLoss(LossModule):
    """NAF's TD loss: ``distance(Q(s, a), r + gamma * V'(s'))`` per transition (``reduction`` "none":
    ``[..., B]``; "mean": a scalar), with Q = V + A as in the module docstring.

    Args:
        actor_network: observation -> mu(s) in the action range (``out_keys``: one action key).
        value_network: observation -> ``[V, L's entries]`` (``1 + D (D + 1) / 2`` numbers).
        action_dim: D.
        loss_function: "l2", "l1" or "smooth_l1" on the TD error.
        reduction: "none" (per transition, the project's populations) or "mean".

    ``forward`` returns ``loss_qvalue`` (and ``value``, ``advantage`` detached, for logging) and
    writes each transition's |y - Q| under ``tensor_keys.priority`` for a prioritised sampler;
    with importance weights in the batch (``priority_weight``) the loss is weighted by them.
    ``target_value_network_params`` is the target network (TorchRL's ``SoftUpdate`` moves it);
    mu needs no target network.
    """

    @dataclass
    class _AcceptedKeys:
        observation: NestedKey = "observation"
        action: NestedKey = "action"
        priority: NestedKey = PRIORITY_KEY
        priority_weight: NestedKey = PRIORITY_WEIGHT_KEY
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        value: NestedKey = "state_value"

    tensor_keys: _AcceptedKeys
    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams  # TorchRL's detached view of mu's own: NAF has no target mu
    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    out_keys = ["loss_qvalue", "value", "advantage"]

    def __init__(self, actor_network: TensorDictModule, value_network: TensorDictModule, action_dim: int, *,
                 loss_function: str = "l2", reduction: str = "none"):
        super().__init__()
        if reduction not in ("none", "mean"):
            raise ValueError(f"reduction must be 'none' or 'mean', got {reduction!r}")
        self.action_dim, self.loss_function, self.reduction = int(action_dim), loss_function, reduction
        self.convert_to_functional(actor_network, "actor_network")
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        keys = self.tensor_keys
        self.in_keys = [keys.observation, keys.action, keys.priority_weight,
                        *(("next", key) for key in (keys.observation, keys.reward, keys.terminated))]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def draw(self, tensordict: TensorDictBase) -> None:
        """NAF's loss draws no random numbers (the project's learners call ``draw`` before each step)."""

    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams) -> "NAFLoss":
        """The TD(0) target only (``gamma``); ``steps_to_next_obs`` in a batch (n-step transitions)
        raises gamma to that power, as TorchRL's estimators do."""
        value_type = value_type or self.default_value_estimator
        if value_type is not ValueEstimators.TD0:
            raise NotImplementedError(f"NAFLoss bootstraps one-step TD(0) targets only, got {value_type}")
        self._value_estimator = TD0Estimator(value_network=None, **hyperparams)
        return self

    def target(self, tensordict: TensorDictBase) -> torch.Tensor:
        """``r + gamma * V'(s')`` where not terminated, ``[..., B]`` (``gamma ** steps`` over n-step
        transitions), without gradient."""
        keys, following = self.tensor_keys, tensordict.get("next")
        with torch.no_grad():
            next_value = module_call(self.value_network, following.get(keys.observation),
                                     self.target_value_network_params)[..., :1]
            reward = following.get(keys.reward)
            estimator = self.value_estimator
            gamma = estimator.gamma.to(reward.device)
            steps = tensordict.get(estimator.tensor_keys.steps_to_next_obs, None)
            if steps is not None:
                gamma = gamma ** steps.view_as(reward)
            return td0_return_estimate(gamma=gamma, next_state_value=next_value, reward=reward,
                                       terminated=following.get(keys.terminated)).squeeze(-1)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        observation = tensordict.get(keys.observation)
        mu = module_call(self.actor_network, observation)
        outputs = module_call(self.value_network, observation)  # [..., 1 + E]: V, then L's entries
        value = outputs[..., 0]
        advantage = naf_advantage(outputs[..., 1:], mu, tensordict.get(keys.action))
        predicted = value + advantage
        target = self.target(tensordict)
        loss = distance_loss(predicted, target, loss_function=self.loss_function)
        weight = tensordict.get(keys.priority_weight, None)
        if weight is not None:
            loss = loss * weight.reshape(loss.shape)
        tensordict.set(keys.priority, (predicted - target).detach().abs())
        if self.reduction == "mean":
            loss = loss.mean()
        return TensorDict({"loss_qvalue": loss, "value": value.detach(), "advantage": advantage.detach()})
