"""What TorchRL's off-policy losses (``SACLoss``, ``TQCLoss``, ``CrossQLoss``, ``REDQLoss``, ``TD3Loss``) share
in a population of stacked members. Each learner's loss and its fused step sit side by side in its own
module (``losses/sac.py``, ``tqc.py``, ``crossq.py``, ``td3.py``, ``redq.py``); this one holds their common
pieces: the members' noise, temperature and Q-network combination, and the plain-tensor pieces the fused
steps are built of (``stacked_values``, ``policy_sample``, ``soft_td_target``, ``td0_target``).

The losses are TorchRL's own; what a population needs on top is small:

- Every tensor has the members first (``[R, B, ...]``) and the networks are stacked
  (``learners.networks``), so TorchRL's ensemble of Q-networks has parameters of shape
  ``[2, R, ...]`` (Q-network, member, ...). Both Q-networks are passed as modules (a list), so
  their initial weights are ours (each member's from its own generator), not TorchRL's
  resampling of one network's weights over all members' range.
- ``reduction="none"``: the losses come back per transition (``[R, B]``); ``member_means``
  turns them into one value per member, whose sum is minimised (each member's gradient its own).
- SAC's (and TQC's) entropy temperature: one per member (``MemberTemperature``), since a shared
  temperature would couple the members.
- The Gaussian noise inside the losses (SAC's reparameterised actions, TD3's target policy
  smoothing) is drawn ahead of each step from each member's own generator (``draw``) and read
  from the minibatch: TorchRL would draw it from torch's global generator, which would make a
  member's numbers depend on the members it is trained with (and a compiled step cannot call
  the members' generators). With the same draws the losses compute what TorchRL's do (tested).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torch.distributions.utils import _sum_rightmost
from torchrl.modules import TanhNormal
from torchrl.modules.distributions.continuous import SafeTanhTransform
from torchrl.objectives.value.functional import td0_return_estimate

from losses.functional import as_alone

ACTION_NOISE_KEY = "action_noise"  # SAC: N(0, I) behind the reparameterised action (root: the actor
#                                    loss's, under "next": the target's)


def member_normal(generators: Sequence[torch.Generator], shape: Sequence[int], like: torch.Tensor) -> torch.Tensor:
    """``[R, *shape]`` standard normal draws, member r's from ``generators[r]``."""
    return torch.stack([torch.randn(tuple(shape), generator=g, dtype=like.dtype, device=like.device)
                        for g in generators])


class DrawnTanhNormal(TanhNormal):
    """TorchRL's ``TanhNormal`` whose reparameterised draw takes its N(0, I) noise as an argument:
    ``tanh(loc + noise * scale)``, scored as TorchRL scores its own draw (``rsample_and_log_prob``).
    Without ``noise`` it is TorchRL's distribution."""

    def __init__(self, loc: torch.Tensor, scale: torch.Tensor, noise: torch.Tensor | None = None, **kwargs):
        self.noise = noise
        super().__init__(loc, scale, **kwargs)

    def rsample_and_log_prob(self, sample_shape=()) -> tuple[torch.Tensor, torch.Tensor]:
        if self.noise is None or tuple(sample_shape) != ():
            return super().rsample_and_log_prob(sample_shape)
        normal = self.root_dist
        preimage = normal.loc + self.noise * normal.scale  # what Normal.rsample computes from its own draw
        transform = self.transforms[0]
        sample = transform(preimage)
        log_prob = self.base_dist.log_prob(preimage) - _sum_rightmost(  # in this order: autograd sums preimage's
            _log_abs_det_jacobian(transform, preimage, sample), len(self.event_shape))  # gradients in it
        return sample, log_prob


def _log_abs_det_jacobian(transform, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``transform.log_abs_det_jacobian(x, y)``; for TorchRL's tanh, its formula with the softplus computed for each
    member as alone (``losses.functional.as_alone``: a minibatch whose rows per member are not a multiple of 8)."""
    if type(transform) is not SafeTanhTransform:
        return transform.log_abs_det_jacobian(x, y)
    return 2.0 * (math.log(2.0) - x - as_alone(torch.nn.functional.softplus, -2.0 * x))


class MemberTemperature:
    """SAC's entropy temperature, one per member (``log_alpha`` of shape ``[R]``), and the members'
    own noise (``draw``; the actor's distribution must be ``DrawnTanhNormal`` reading
    ``ACTION_NOISE_KEY``), for TorchRL's ``SACLoss`` and the losses built like it (``TQCLoss``,
    ``CrossQLoss``); their losses come back per transition (``reduction="none"``)."""

    def __init__(self, *args, members: int, generators: Sequence[torch.Generator] | None = None, **kwargs):
        # the TorchRL loss (next in the MRO) per transition: member_means averages per member
        super().__init__(*args, reduction="none", scalar_output_mode="exclude", **kwargs)
        self.members = members
        self.generators = list(generators) if generators is not None else None
        log_alpha = torch.full((members,), math.log(float(self.alpha_init)), device=self.alpha_init.device)
        del self.log_alpha
        if self.fixed_alpha:
            self.register_buffer("log_alpha", log_alpha)
        else:
            self.log_alpha = torch.nn.Parameter(log_alpha)
        self._alpha_shape = (members, 1)  # broadcasts against [R, B] log-probabilities

    def draw(self, tensordict: TensorDictBase) -> None:
        """Each member's N(0, I) noise for this minibatch (``[R, B, D]``) into ``tensordict``: the
        target's (under ``"next"``) first, then the actor loss's, both from the member's generator."""
        action = tensordict.get("action")
        noise = member_normal(self.generators, (2, *action.shape[1:]), action)
        tensordict.set(("next", ACTION_NOISE_KEY), noise[:, 0])
        tensordict.set(ACTION_NOISE_KEY, noise[:, 1])

    @property
    def _alpha(self) -> torch.Tensor:
        if self.min_log_alpha is not None or self.max_log_alpha is not None:
            self.log_alpha.data.clamp_(self.min_log_alpha, self.max_log_alpha)
        with torch.no_grad():
            return self.log_alpha.exp().reshape(self._alpha_shape)

    def _with_target_alpha(self, compute, tensordict: TensorDictBase) -> torch.Tensor:
        # The targets scale values with one more trailing dimension by alpha ([Q-nets, R, B, 1]
        # for SAC, [R, B, atoms] for TQC): the temperature broadcasts as [R, 1, 1] there.
        self._alpha_shape = (self.members, 1, 1)
        try:
            return compute(tensordict)
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


def q_reduce(values: torch.Tensor, pessimism: float | None) -> torch.Tensor:
    """The Q-networks' values ``[Q, ...]`` made one value, as the target and the actor read them: their
    minimum (``pessimism`` None: clipped double Q, TorchRL's), or ``mean - pessimism * std`` over the
    networks (the population standard deviation, floored at 1e-6 so that its gradient stays finite where
    the networks agree). With two networks std is half their distance, so 1 is the minimum, 0 their mean,
    and a negative value optimism (tactical optimism's form, Moskovitz et al., 2021)."""
    if pessimism is None:
        return values.min(0)[0]
    mean = values.mean(0)
    if pessimism == 0:
        return mean
    return mean - pessimism * values.var(0, correction=0).clamp_min(1e-12).sqrt()


def stackable_critic(loss) -> bool:
    """Whether ``loss``'s Q-networks compute on plain stacked tensors (``stacked_values``): stacked
    MLPs (plain, or DroQ's with dropout and layer norm) or BRO's residual networks."""
    critic = getattr(loss.qvalue_network, "module", None)
    return hasattr(critic, "forward_named") or hasattr(getattr(critic, "net", None), "forward_with")


def owns_actor(loss, actor_net: nn.Module) -> bool:
    """Whether ``actor_net``'s parameters are the ones ``loss`` trains."""
    return set(map(id, loss.actor_network_params.values(True, True))) == set(map(id, actor_net.parameters()))


class Copies(torch.autograd.Function):
    """``x`` repeated ``copies`` times along a new first dimension, whose gradient sums the copies'
    gradients as autograd accumulates those of a loop that feeds ``x`` to each copy in turn: the
    last copy's first, then each earlier one added (``expand``'s gradient sums in another order)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, copies: int) -> torch.Tensor:
        ctx.copies = copies
        return x.unsqueeze(0).expand(copies, *x.shape).contiguous()

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        total = grad[ctx.copies - 1]
        for i in range(ctx.copies - 2, -1, -1):
            total = total + grad[i]
        return total, None


def stacked_values(loss, inputs: torch.Tensor, params: TensorDictBase, loop_order: bool = False,
                    training: bool = True) -> torch.Tensor:
    """Every Q-network's values ``[Q, R, B, 1]`` for inputs ``[R, B, obs + action]`` and stacked
    parameters ``[Q, R, ...]``, in one pass over ``Q * R`` networks (each computes alone, as in
    TorchRL's loop over the Q-networks, DroQ's dropout masks drawn in that loop's order).
    ``loop_order``: the inputs' gradient summed over the Q-networks in the order autograd sums the
    loop's (``Copies``; needed where more than one Q-network's gradient reaches the inputs, as in
    TQC's actor loss; REDQ's step, not held to TorchRL's bits, keeps ``expand``'s sum).
    CrossQ's batch-normalised Q-networks (``forward_stacked``) normalise by each network's batch
    statistics in ``training`` (updating its running estimates in place), else by those estimates."""
    critic = loss.qvalue_network.module
    named = {name: value.flatten(0, 1) for name, value in params["module"].flatten_keys(".").items()}
    q, members = next(iter(params["module"].values(True, True))).shape[:2]
    x = (Copies.apply(inputs, q) if loop_order else inputs.expand(q, *inputs.shape)).reshape(
        q * members, *inputs.shape[1:])
    if hasattr(critic, "forward_stacked"):  # CrossQ's batch-normalised Q-network
        values = critic.forward_stacked(x, named, training)
    elif hasattr(critic, "forward_named"):  # BRO's residual Q-network
        values = critic.forward_named(x, named)
    else:
        pairs = [(named[f"net.layers.{i}.weight"], named[f"net.layers.{i}.bias"]) for i in range(len(critic.net.layers))]
        if hasattr(critic.net, "dropouts"):
            # DroQ's regularised MLP: its dropout masks drawn as TorchRL's loop over the Q-networks draws them
            norms = None if critic.net.norms is None else [
                (named[f"net.norms.{i}.weight"], named[f"net.norms.{i}.bias"]) for i in range(len(critic.net.norms))]
            values = critic.net.forward_with(x, pairs, norms, copies=q)
        else:
            values = critic.net.forward_with(x, pairs)
    return values.reshape(q, members, *inputs.shape[1:-1], -1)


def draws_masks(loss) -> bool:
    """Whether ``loss``'s Q-networks draw dropout masks when they compute (DroQ's, training)."""
    dropouts = getattr(getattr(loss.qvalue_network.module, "net", None), "dropouts", None)
    return bool(dropouts) and dropouts[0].active


def check_no_masks(batch: TensorDictBase) -> None:
    for key in (("collector", "mask"), "shifted_valid"):  # TorchRL's loss masks: not written here
        if key in batch.keys(True):
            raise ValueError(f"the fused off-policy steps do not apply loss masks ({key!r} in the minibatch)")


def policy_sample(actor_net: nn.Module, observation: torch.Tensor,
                   noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The actor's reparameterised action ``tanh(loc + noise * scale)`` at ``observation`` and its
    log-probability, as TorchRL's losses draw and score it (``DrawnTanhNormal``)."""
    loc, scale = actor_net(observation)
    return DrawnTanhNormal(loc, scale, noise, low=-1.0, high=1.0).rsample_and_log_prob()


CRITIC_EXTRAS = ("privileged", "history")  # what Q-networks may read besides (s, a), in this order


def q_input(tensordict: TensorDictBase, observation: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """What the Q-networks read, concatenated in their modules' key order: the observation, then what the
    transitions hold of ``CRITIC_EXTRAS`` (the car's true state, ``algo.td.privileged_critic``; its past
    observations and actions, ``algo.td.critic_history``), then the action."""
    keys = tensordict.keys()
    extras = [tensordict.get(key) for key in CRITIC_EXTRAS if key in keys]
    return torch.cat([observation, *extras, action], -1)


@torch.no_grad()
def soft_td_target(loss, actor_net: nn.Module, batch: TensorDictBase, params: TensorDictBase,
                    alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The soft TD(0) target ``[R, B]`` as TorchRL's SAC and REDQ losses compute it:
    ``r + gamma * (min_j Q_j(s', a') - alpha * log pi(a'|s'))`` (``gamma ** steps`` over n-step
    transitions) with ``a'`` drawn with the noise under ``("next", ACTION_NOISE_KEY)``, the minimum
    over the Q-networks of ``params`` (``[Q, R, ...]``; ``q_reduce`` with the loss's pessimism) and ``alpha`` the temperature ``[R, 1, 1]``;
    and ``log pi(a'|s')`` ``[R, B]``."""
    following = batch.get("next")
    next_observation = following.get("observation")
    next_action, next_log_prob = policy_sample(actor_net, next_observation, following.get(ACTION_NOISE_KEY))
    next_values = stacked_values(loss, q_input(following, next_observation, next_action), params)
    # subtracting the same number from every network's value keeps the minimum's bits: the same as TorchRL's
    # (next_values - alpha * log_prob).min(0) where no pessimism is set
    next_value = q_reduce(next_values, getattr(loss, "pessimism", None)) - alpha * next_log_prob.unsqueeze(-1)
    return td0_target(loss, batch, next_value), next_log_prob


def td0_target(loss, batch: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
    """``r + gamma * next_value`` where not terminated, ``[R, B]`` (``gamma ** steps`` over n-step
    transitions), as the losses' TD(0) value estimator computes it from ``next_value`` ``[R, B, 1]``."""
    return td0_returns(loss, batch, next_value).squeeze(-1)


def td0_returns(loss, batch: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
    """``td0_target`` for every entry of ``next_value`` ``[R, B, k]`` (TQC's k target atoms), the
    reward, termination and steps taken to its shape as TorchRL's losses do: ``[R, B, k]``."""
    keys, following = loss.tensor_keys, batch.get("next")
    reward = following.get(keys.reward)
    estimator = loss.value_estimator
    gamma = estimator.gamma.to(reward.device)
    steps = batch.get(estimator.tensor_keys.steps_to_next_obs, None)
    if steps is not None:
        gamma = gamma ** steps.view_as(reward).expand_as(next_value)
    return td0_return_estimate(gamma=gamma, next_state_value=next_value, reward=reward.expand_as(next_value),
                               terminated=following.get(keys.terminated).expand_as(next_value))


def member_means(values: torch.Tensor) -> torch.Tensor:
    """``[R, B]`` per-transition values -> ``[R]``, one mean per member."""
    return values.reshape(values.shape[0], -1).mean(-1)
