"""Trust-PCL (Nachum, Norouzi, Xu and Schuurmans, 2018) as a TorchRL loss.

Trust-PCL trains a policy pi and a value function V off-policy, on sub-episodes of d steps drawn
from a replay memory of episodes, so that they satisfy the path consistency of returns
regularised by the relative entropy to a lagged copy of the policy (pi~, the trust region):

    C(s_t..t+d) = -V(s_t) + gamma^d V~(s_t+d)
                  + sum_i<d gamma^i [ r_t+i - (tau + lambda) log pi(a_t+i | s_t+i) + lambda log pi~(a_t+i | s_t+i) ],

with tau the entropy coefficient (0 in the authors' continuous-control runs), V~ the lagged
value network (the authors' ``use_target_values``), and d shortened where the episode ends
inside the sub-episode (there V~ of the episode's last state is taken, or 0 where the episode
terminated). Both networks descend the consistency's square as the authors' code does: the
value network by ``1/2 C^2`` through V(s_t) (``critic_weight`` x ``-C V(s_t)``, C held fixed), the
policy by ``-C sum_i gamma^i log pi(a_t+i | s_t+i)`` (C held fixed: the direction of 1/2 C^2's
gradient, without its factor tau + lambda), each with C clipped to ``[-clip, clip]`` when ``clip``
is set (the authors' ``clip_adv``).

The coefficient lambda follows the trust-region constraint (``relative_entropy_coefficient``): the
lambda at which the optimal regularised policy's divergence from pi~, estimated from recent
episodes' total rewards R_j as ``E_p[R / lambda] - log mean_j exp(R_j / lambda)`` with
``p_j ~ exp(R_j / lambda)``, equals ``max_divergence`` times the episode length, found by bisection
on [0, 1000]; lambda moves to it by 1% per gradient step (``coefficient_targets``, ``move_coefficient``).

What differs from the authors' code, deliberately: the policy and the value network have an Adam
optimiser each (theirs: one for both), gradients are not clipped by their global norm (theirs: at 40),
sub-episodes are drawn uniformly from the memory (theirs: nearly uniform, a slight preference for the
newest), the actor is this project's tanh-squashed Gaussian with a state-dependent scale (theirs: a
Gaussian with a learned state-independent deviation).

Populations: every tensor has the members first; a sub-episode batch is ``[R, B, d]`` with a
``mask`` of its valid steps (``collectors.replay.sample_sub_episodes``), lambda is one per member.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torchrl.modules import TanhNormal
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators

from losses.common import module_call

MASK_KEY = "mask"  # a sub-episode's valid steps ([..., d], a prefix)
LAMBDA_RANGE = (0.0, 1000.0)  # the bisection's bracket (the authors')
LAMBDA_TOLERANCE = 0.1  # its resolution: 14 halvings of the bracket
FEWEST_EPISODES = 9  # with fewer episodes the bisection is not run: the bracket's middle (the authors' rule)


def discounted_sums(values: torch.Tensor, mask: torch.Tensor, gamma: float) -> torch.Tensor:
    """``sum_i gamma^i values[..., i]`` over the steps ``mask`` ``[..., d]`` marks valid -> ``[...]``
    (invalid steps contribute nothing, whatever their values)."""
    powers = gamma ** torch.arange(values.shape[-1], dtype=values.dtype, device=values.device)
    return torch.where(mask, values * powers, values.new_zeros(())).sum(-1)


def path_consistency(value: torch.Tensor, final_value: torch.Tensor, rewards: torch.Tensor,
                     log_probs: torch.Tensor, lagged_log_probs: torch.Tensor, mask: torch.Tensor, gamma: float,
                     entropy: float, coefficient: torch.Tensor) -> torch.Tensor:
    """The consistency C ``[...]`` of sub-episodes (module docstring): ``value`` V(s_t) ``[...]``,
    ``final_value`` the value after the last valid step ``[...]`` (0 where the episode terminated),
    ``rewards`` and the log-probabilities ``[..., d]`` over the steps ``mask`` marks valid (a prefix of
    length L; gamma^L discounts the final value), ``entropy`` tau and ``coefficient`` lambda
    (broadcastable to ``[...]``)."""
    coefficient = torch.as_tensor(coefficient, dtype=value.dtype, device=value.device).unsqueeze(-1)
    regularised = rewards - (entropy + coefficient) * log_probs + coefficient * lagged_log_probs
    length = mask.sum(-1).to(value.dtype)
    return -value + gamma ** length * final_value + discounted_sums(regularised, mask, gamma)


def trajectory_divergence(returns: Sequence[float], coefficient: float) -> float:
    """``KL(pi* || pi~)`` of the regularised optimum at ``coefficient`` lambda, estimated from episodes
    of pi~ with total rewards ``returns``: ``E_p[R / lambda] - log mean exp(R / lambda)``, p ~ exp(R / lambda)
    (float64 through ``math``: the same bits on every CPU)."""
    top = max(returns)
    log_mean = top / coefficient + math.log(math.fsum(math.exp((r - top) / coefficient) for r in returns)
                                            / len(returns))
    weighted = math.fsum(math.exp(r / coefficient - log_mean) * r / coefficient for r in returns) / len(returns)
    return weighted - log_mean


def relative_entropy_coefficient(returns: Sequence[float], max_divergence: float, episode_steps: int) -> float:
    """The lambda whose ``trajectory_divergence`` is ``max_divergence * episode_steps``, by bisection on
    ``LAMBDA_RANGE`` to ``LAMBDA_TOLERANCE`` (a larger lambda, a smaller divergence); the bracket's middle
    with fewer than ``FEWEST_EPISODES`` episodes (the estimate would be noise)."""
    left, right = LAMBDA_RANGE
    if len(returns) < FEWEST_EPISODES:
        return (left + right) / 2
    desired = max_divergence * episode_steps
    for _ in range(max(4, 1 + int(math.log((right - left) / LAMBDA_TOLERANCE) / math.log(2.0)))):
        middle = (left + right) / 2
        if trajectory_divergence(returns, middle) > desired:
            left = middle
        else:
            right = middle
    return (left + right) / 2


class TrustPCLLoss(LossModule):
    """Trust-PCL's two losses on a batch of sub-episodes ``[..., B, d]`` (module docstring).

    Args:
        actor_network: observation -> (loc, scale) of a Gaussian squashed by tanh into [-1, 1]
            (TorchRL's ``TanhNormal``, as SAC's actor).
        value_network: observation -> V(s) (one number).
        rollout: d, the sub-episodes' length (a batch may be shorter; it is read from the batch).
        entropy: tau, the entropy coefficient (0: none, as the authors ran continuous control).
        max_divergence: the trust region's epsilon, per step of an episode.
        clip: C is clipped to [-clip, clip] in both gradients (None: not clipped).
        critic_weight: the value loss's weight.
        members: lambda's count (one per member of a population; 1 alone).

    ``forward`` returns ``loss_actor``, ``loss_value`` (per sub-episode, ``[..., B]``) and
    ``consistency`` (C, detached). ``target_actor_network_params`` and ``target_value_network_params``
    are the lagged policy and value (TorchRL's ``SoftUpdate`` moves them: ``tau`` = 1 - the lag).
    ``coefficient`` (lambda, ``[members]``, float64) is saved with the loss's state.
    """

    @dataclass
    class _AcceptedKeys:
        observation: NestedKey = "observation"
        action: NestedKey = "action"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        mask: NestedKey = MASK_KEY

    tensor_keys: _AcceptedKeys
    actor_network: TensorDictModule
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    value_network: TensorDictModule
    value_network_params: TensorDictParams
    target_value_network_params: TensorDictParams
    default_keys = _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    out_keys = ["loss_actor", "loss_value", "consistency"]

    def __init__(self, actor_network: TensorDictModule, value_network: TensorDictModule, *, gamma: float,
                 rollout: int, entropy: float = 0.0, max_divergence: float = 0.001, clip: float | None = 1.0,
                 critic_weight: float = 1.0, members: int = 1, coefficient: float = 0.0):
        super().__init__()
        if rollout < 1:
            raise ValueError(f"rollout must be at least 1, got {rollout}")
        self.gamma, self.rollout, self.entropy = float(gamma), int(rollout), float(entropy)
        self.max_divergence, self.clip, self.critic_weight = float(max_divergence), clip, float(critic_weight)
        self.convert_to_functional(actor_network, "actor_network", create_target_params=True)
        self.convert_to_functional(value_network, "value_network", create_target_params=True)
        self.register_buffer("coefficient", torch.full((members,), float(coefficient), dtype=torch.float64))
        keys = self.tensor_keys
        self.in_keys = [keys.observation, keys.action, keys.mask,
                        *(("next", key) for key in (keys.observation, keys.reward, keys.terminated))]

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def make_value_estimator(self, value_type=None, **hyperparams) -> "TrustPCLLoss":
        """Trust-PCL's targets are its own path consistencies (``gamma`` is set at construction)."""
        return self

    def draw(self, tensordict: TensorDictBase) -> None:
        """Trust-PCL's loss draws no random numbers (the project's learners call ``draw`` before each step)."""

    def log_prob(self, observation: torch.Tensor, action: torch.Tensor, lagged: bool = False) -> torch.Tensor:
        """log pi(action | observation) (the lagged policy's with ``lagged``), summed over action dimensions."""
        loc, scale = module_call(self.actor_network, observation, self.target_actor_network_params if lagged else None)
        return TanhNormal(loc, scale, low=-1.0, high=1.0).log_prob(action)

    def coefficient_targets(self, returns: Sequence[Sequence[float]], episode_steps: int) -> torch.Tensor:
        """The lambda the trust region sets for each member from its recent episodes' total rewards
        ``returns[r]`` (``relative_entropy_coefficient``), ``[R]`` float64."""
        return torch.tensor([relative_entropy_coefficient(r, self.max_divergence, episode_steps) for r in returns],
                            dtype=torch.float64, device=self.coefficient.device)

    @torch.no_grad()
    def move_coefficient(self, targets: torch.Tensor) -> None:
        """One gradient step's move of lambda: ``lambda <- 0.99 lambda + 0.01 target`` (the authors' smoothing)."""
        self.coefficient.mul_(0.99).add_(0.01 * targets)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        mask = tensordict.get(keys.mask)
        following = tensordict.get("next")
        observation = tensordict.get(keys.observation)
        action = tensordict.get(keys.action)
        log_probs = self.log_prob(observation, action)
        with torch.no_grad():
            lagged_log_probs = self.log_prob(observation, action, lagged=True)
            length = mask.sum(-1, keepdim=True)  # the sub-episode's valid prefix: its last step is length - 1
            last = (length - 1).clamp_min(0)
            final_observation = following.get(keys.observation).gather(
                -2, last.unsqueeze(-1).expand(*last.shape, observation.shape[-1])).squeeze(-2)
            terminated = following.get(keys.terminated).squeeze(-1).gather(-1, last).squeeze(-1)
            final_value = module_call(self.value_network, final_observation,
                                      self.target_value_network_params).squeeze(-1) * (~terminated)
        value = module_call(self.value_network, observation[..., 0, :]).squeeze(-1)
        coefficient = self.coefficient.to(value.dtype)
        if value.dim() > 1:  # a population's [R, B]: each member's own lambda
            coefficient = coefficient.reshape(-1, *([1] * (value.dim() - 1)))
        consistency = path_consistency(value, final_value, following.get(keys.reward).squeeze(-1), log_probs,
                                       lagged_log_probs, mask, self.gamma, self.entropy, coefficient)
        held = consistency.detach()
        if self.clip is not None:
            held = held.clamp(-self.clip, self.clip)
        loss_actor = -held * discounted_sums(log_probs, mask, self.gamma)
        loss_value = -self.critic_weight * held * value
        return TensorDict({"loss_actor": loss_actor, "loss_value": loss_value, "consistency": consistency.detach()})
