"""TorchRL's off-policy losses (``SACLoss``, ``TQCLoss``, ``CrossQLoss``, ``REDQLoss``, ``TD3Loss``) for
a population of stacked members.

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

import contextlib
import math
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torch import nn
from torch.distributions.utils import _sum_rightmost
from torchrl.modules import TanhNormal
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.objectives import CrossQLoss, REDQLoss, SACLoss, TD3Loss, TQCLoss
from torchrl.objectives.utils import distance_loss
from torchrl.objectives.value.functional import td0_return_estimate

from losses.common import PRIORITY_KEY  # noqa: F401  (TorchRL's SAC writes each transition's |TD error| there)
from losses.common import PRIORITY_WEIGHT_KEY

ACTION_NOISE_KEY = "action_noise"  # SAC: N(0, I) behind the reparameterised action (root: the actor
#                                    loss's, under "next": the target's)
SMOOTHING_KEY = "smoothing_noise"  # TD3: the clipped target smoothing noise under "next" (zeros at the root)


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
        log_prob = self.base_dist.log_prob(preimage) - _sum_rightmost(
            transform.log_abs_det_jacobian(preimage, sample), len(self.event_shape))
        return sample, log_prob


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


def _stackable_critic(loss) -> bool:
    """Whether ``loss``'s Q-networks compute on plain stacked tensors (``_stacked_values``): stacked
    MLPs (plain, or DroQ's with dropout and layer norm) or BRO's residual networks."""
    critic = getattr(loss.qvalue_network, "module", None)
    return hasattr(critic, "forward_named") or hasattr(getattr(critic, "net", None), "forward_with")


def _owns_actor(loss, actor_net: nn.Module) -> bool:
    """Whether ``actor_net``'s parameters are the ones ``loss`` trains."""
    return set(map(id, loss.actor_network_params.values(True, True))) == set(map(id, actor_net.parameters()))


def fused_sac_available(loss, actor_net: nn.Module) -> bool:
    """Whether ``fused_sac_losses`` computes ``loss``'s step: SAC (not TQC or CrossQ) eagerly, with
    Q-networks that are stacked MLPs (plain or DroQ's) or BRO's residual networks,
    and the actor network the loss's own."""
    return (type(loss) is MemberSACLoss and loss.deactivate_vmap and getattr(loss, "_version", 2) == 2
            and not loss.skip_done_states and _stackable_critic(loss) and _owns_actor(loss, actor_net))


class _Copies(torch.autograd.Function):
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


def _stacked_values(loss, inputs: torch.Tensor, params: TensorDictBase, loop_order: bool = False,
                    training: bool = True) -> torch.Tensor:
    """Every Q-network's values ``[Q, R, B, 1]`` for inputs ``[R, B, obs + action]`` and stacked
    parameters ``[Q, R, ...]``, in one pass over ``Q * R`` networks (each computes alone, as in
    TorchRL's loop over the Q-networks, DroQ's dropout masks drawn in that loop's order).
    ``loop_order``: the inputs' gradient summed over the Q-networks in the order autograd sums the
    loop's (``_Copies``; needed where more than one Q-network's gradient reaches the inputs, as in
    TQC's actor loss; REDQ's step, not held to TorchRL's bits, keeps ``expand``'s sum).
    CrossQ's batch-normalised Q-networks (``forward_stacked``) normalise by each network's batch
    statistics in ``training`` (updating its running estimates in place), else by those estimates."""
    critic = loss.qvalue_network.module
    named = {name: value.flatten(0, 1) for name, value in params["module"].flatten_keys(".").items()}
    q, members = next(iter(params["module"].values(True, True))).shape[:2]
    x = (_Copies.apply(inputs, q) if loop_order else inputs.expand(q, *inputs.shape)).reshape(
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


def _draws_masks(loss) -> bool:
    """Whether ``loss``'s Q-networks draw dropout masks when they compute (DroQ's, training)."""
    dropouts = getattr(getattr(loss.qvalue_network.module, "net", None), "dropouts", None)
    return bool(dropouts) and dropouts[0].active


def _check_no_masks(batch: TensorDictBase) -> None:
    for key in (("collector", "mask"), "shifted_valid"):  # TorchRL's loss masks: not written here
        if key in batch.keys(True):
            raise ValueError(f"the fused off-policy steps do not apply loss masks ({key!r} in the minibatch)")


def _policy_sample(actor_net: nn.Module, observation: torch.Tensor,
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
def _soft_td_target(loss, actor_net: nn.Module, batch: TensorDictBase, params: TensorDictBase,
                    alpha: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The soft TD(0) target ``[R, B]`` as TorchRL's SAC and REDQ losses compute it:
    ``r + gamma * (min_j Q_j(s', a') - alpha * log pi(a'|s'))`` (``gamma ** steps`` over n-step
    transitions) with ``a'`` drawn with the noise under ``("next", ACTION_NOISE_KEY)``, the minimum
    over the Q-networks of ``params`` (``[Q, R, ...]``; ``q_reduce`` with the loss's pessimism) and ``alpha`` the temperature ``[R, 1, 1]``;
    and ``log pi(a'|s')`` ``[R, B]``."""
    following = batch.get("next")
    next_observation = following.get("observation")
    next_action, next_log_prob = _policy_sample(actor_net, next_observation, following.get(ACTION_NOISE_KEY))
    next_values = _stacked_values(loss, q_input(following, next_observation, next_action), params)
    # subtracting the same number from every network's value keeps the minimum's bits: the same as TorchRL's
    # (next_values - alpha * log_prob).min(0) where no pessimism is set
    next_value = q_reduce(next_values, getattr(loss, "pessimism", None)) - alpha * next_log_prob.unsqueeze(-1)
    return _td0_target(loss, batch, next_value), next_log_prob


def _td0_target(loss, batch: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
    """``r + gamma * next_value`` where not terminated, ``[R, B]`` (``gamma ** steps`` over n-step
    transitions), as the losses' TD(0) value estimator computes it from ``next_value`` ``[R, B, 1]``."""
    return _td0_returns(loss, batch, next_value).squeeze(-1)


def _td0_returns(loss, batch: TensorDictBase, next_value: torch.Tensor) -> torch.Tensor:
    """``_td0_target`` for every entry of ``next_value`` ``[R, B, k]`` (TQC's k target atoms), the
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


def fused_sac_losses(loss: "MemberSACLoss", actor_net: nn.Module,
                     batch: TensorDictBase) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """``MemberSACLoss``'s three losses per member (``member_means`` of ``loss(batch)``) and the
    minibatch's priorities, computed on plain tensors: the same operations in the same order as
    TorchRL's ``SACLoss`` (v2: ``_compute_target_v2``, ``qvalue_v2_loss``, ``actor_loss``,
    ``_alpha_loss``, importance weights when the minibatch has them), so the same bits, forward
    and backward (tested), without its TensorDict and parameter-swapping work per call, which
    costs more than the arithmetic at these sizes. Where ``fused_sac_available`` holds."""
    _check_no_masks(batch)
    keys = loss.tensor_keys
    weights = batch.get(keys.priority_weight, None) if loss.use_prioritized_weights in (True, "auto") else None
    observation = batch.get("observation")
    members = observation.shape[0]
    target, _ = _soft_td_target(loss, actor_net, batch, loss.target_qvalue_network_params,
                                loss._alpha.reshape(members, 1, 1))
    predicted = _stacked_values(loss, q_input(batch, observation, batch.get("action")),
                                loss.qvalue_network_params).squeeze(-1)
    td_error = abs(predicted - target)
    loss_qvalue = distance_loss(predicted, target.expand_as(predicted), loss_function=loss.loss_function).sum(0)
    action, log_prob = _policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
    min_q = q_reduce(_stacked_values(loss, q_input(batch, observation, action), loss.qvalue_network_params.detach()),
                     loss.pessimism).squeeze(-1)
    loss_actor = loss._alpha * log_prob - min_q
    loss_alpha = loss._alpha_loss(log_prob.detach())
    if weights is not None:
        loss_qvalue, loss_actor, loss_alpha = loss_qvalue * weights, loss_actor * weights, loss_alpha * weights
    losses = {"loss_qvalue": member_means(loss_qvalue), "loss_actor": member_means(loss_actor),
              "loss_alpha": member_means(loss_alpha)}
    return losses, td_error.detach().max(0)[0]


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
        _check_no_masks(batch)
        weights = batch.get(PRIORITY_WEIGHT_KEY, None)
        observation = batch.get("observation")
        members = observation.shape[0]
        if self.subsets is None or self.subsets.shape[1] != members:
            raise RuntimeError("population_losses needs each member's subset of target networks: call draw(batch) first")
        rows = torch.arange(members, device=self.subsets.device)
        chosen = self.target_qvalue_network_params.apply(lambda value: value[self.subsets, rows],  # [subset, R, ...]
                                                         batch_size=[self.subsets.shape[0]])
        alpha = self._alpha.reshape(members, 1)
        target, next_log_prob = _soft_td_target(self, actor_net, batch, chosen, alpha.unsqueeze(-1))
        predicted = _stacked_values(self, q_input(batch, observation, batch.get("action")),
                                    self.qvalue_network_params).squeeze(-1)  # [Q, R, B]
        td_error = abs(predicted - target)
        loss_qvalue = distance_loss(predicted, target.expand_as(predicted), loss_function=self.loss_function).mean(0)
        losses = {"loss_qvalue": loss_qvalue}
        if actor:
            action, log_prob = _policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
            values = _stacked_values(self, q_input(batch, observation, action),
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
    return isinstance(loss, MemberREDQLoss) and loss.deactivate_vmap and _stackable_critic(loss) \
        and _owns_actor(loss, actor_net)


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
            and not loss.skip_done_states and _stackable_critic(loss) and _owns_actor(loss, actor_net))


def fused_tqc_losses(loss: "MemberTQCLoss", actor_net: nn.Module,
                     batch: TensorDictBase) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """``MemberTQCLoss``'s three losses per member (``member_means`` of ``loss(batch)``) and the
    minibatch's priorities on plain tensors, TorchRL's ``TQCLoss`` operation for operation (tested bit
    for bit): the target pools every target Q-network's quantiles at ``(s', a')``, sorts them and drops
    the ``top_quantiles_to_drop_per_net * Q`` highest, ``r + gamma * (atom - alpha * log pi(a'|s'))`` per
    kept atom; each Q-network's quantile Huber loss against those atoms (``quantile_huber_loss``); the
    actor's ``alpha * log pi(a|s)`` minus the mean of every quantile of every (detached) Q-network."""
    _check_no_masks(batch)
    weights = loss._maybe_get_priority_weight(batch)
    observation = batch.get("observation")
    members = observation.shape[0]
    with torch.no_grad():
        following = batch.get("next")
        next_observation = following.get("observation")
        next_action, next_log_prob = _policy_sample(actor_net, next_observation, following.get(ACTION_NOISE_KEY))
        atoms = _stacked_values(loss, torch.cat([next_observation, next_action], -1),
                                loss.target_qvalue_network_params)  # [Q, R, B, n]
        atoms = atoms.movedim(0, -2).flatten(-2)
        keep = atoms.shape[-1] - loss.top_quantiles_to_drop_per_net * loss.num_qvalue_nets
        atoms = torch.sort(atoms, dim=-1).values[..., :keep]
        next_value = atoms - loss._alpha.reshape(members, 1, 1) * next_log_prob.unsqueeze(-1)
        target = _td0_returns(loss, batch, next_value)
    quantiles = _stacked_values(loss, torch.cat([observation, batch.get("action")], -1), loss.qvalue_network_params)
    loss_qvalue, td_error = quantile_huber_loss(quantiles, target.unsqueeze(0))
    loss_qvalue = loss_qvalue.sum(0)
    action, log_prob = _policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
    values = _stacked_values(loss, torch.cat([observation, action], -1), loss.qvalue_network_params.detach(),
                             loop_order=True)
    loss_actor = loss._alpha * log_prob - values.mean(dim=(0, -1))
    loss_alpha = loss._alpha_loss(log_prob.detach())
    if weights is not None:
        loss_qvalue, loss_actor, loss_alpha = loss_qvalue * weights, loss_actor * weights, loss_alpha * weights
    losses = {"loss_qvalue": member_means(loss_qvalue), "loss_actor": member_means(loss_actor),
              "loss_alpha": member_means(loss_alpha)}
    return losses, td_error.max(0)[0]


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
            and _owns_actor(loss, actor_net))


def fused_crossq_critic_losses(loss: "MemberCrossQLoss", actor_net: nn.Module,
                               batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """``MemberCrossQLoss.qvalue_loss`` per member (``member_means``) and its priorities, on plain
    tensors (tested bit for bit, running estimates included): the next action drawn with the noise
    under ``("next", ACTION_NOISE_KEY)``, (s, a) and (s', a') scored in one batch-normalised pass per
    Q-network, the target ``r + gamma * (min_j Q_j(s', a') - alpha * log pi(a'|s'))`` detached."""
    _check_no_masks(batch)
    following = batch.get("next")
    with torch.no_grad():
        next_observation = following.get("observation")
        next_action, next_log_prob = _policy_sample(actor_net, next_observation, following.get(ACTION_NOISE_KEY))
    joint = torch.cat([torch.cat([batch.get("observation"), batch.get("action")], -1),
                       torch.cat([next_observation, next_action], -1)], dim=1)
    values = _stacked_values(loss, joint, loss.qvalue_network_params, loop_order=True, training=True)
    current, following_values = values.split(batch.batch_size[1], dim=2)  # [Q, R, B, 1] each
    next_value = (following_values.min(0)[0] - loss._alpha.unsqueeze(-1) * next_log_prob.unsqueeze(-1)).detach()
    target = _td0_target(loss, batch, next_value)
    predicted = current.squeeze(-1)
    loss_qvalue = distance_loss(predicted, target.expand_as(predicted), loss_function=loss.loss_function).sum(0)
    return member_means(loss_qvalue), (predicted - target).abs().detach().max(0)[0]


def fused_crossq_actor_losses(loss: "MemberCrossQLoss", actor_net: nn.Module,
                              batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """TorchRL's ``CrossQLoss.actor_loss`` and ``MemberCrossQLoss.alpha_loss`` per member, on plain
    tensors (tested bit for bit): ``alpha * log pi(a|s) - min_j Q_j(s, a)`` with the Q-networks
    detached and in evaluation mode (their running estimates), and the temperature's loss."""
    _check_no_masks(batch)
    observation = batch.get("observation")
    action, log_prob = _policy_sample(actor_net, observation, batch.get(ACTION_NOISE_KEY))
    values = _stacked_values(loss, torch.cat([observation, action], -1), loss.qvalue_network_params.detach(),
                             loop_order=True, training=False)
    loss_actor = loss._alpha * log_prob - values.min(0)[0].squeeze(-1)
    return member_means(loss_actor), member_means(loss._alpha_loss(log_prob.detach()))


def member_means(values: torch.Tensor) -> torch.Tensor:
    """``[R, B]`` per-transition values -> ``[R]``, one mean per member."""
    return values.reshape(values.shape[0], -1).mean(-1)


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
    return (type(loss) is MemberTD3Loss and loss.deactivate_vmap and _stackable_critic(loss)
            and _owns_actor(loss, actor_net) and isinstance(actor_net, nn.Sequential) and len(actor_net) == 2
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
    _check_no_masks(batch)
    weights = loss._maybe_get_priority_weight(batch)
    following = batch.get("next")
    body = actor_net[0]
    with torch.no_grad():
        next_observation = following.get("observation")
        target_actor = _pairs(loss.target_actor_network_params, ("module", "net", "0", "layers"), len(body.layers))
        next_action = (torch.tanh(body.forward_with(next_observation, target_actor)) + following.get(SMOOTHING_KEY))
        next_action = next_action.clamp(loss.min_action, loss.max_action)
        next_values = _stacked_values(loss, torch.cat([next_observation, next_action], -1),
                                      loss.target_qvalue_network_params).squeeze(-1)
    target = _td0_target(loss, batch, next_values.min(0)[0].unsqueeze(-1))
    predicted = _stacked_values(loss, torch.cat([batch.get("observation"), batch.get("action")], -1),
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
    zero), unless the Q-networks draw dropout masks, whose draws must stay as TorchRL's."""
    _check_no_masks(batch)
    weights = loss._maybe_get_priority_weight(batch)
    observation = batch.get("observation")
    action = actor_net(observation) + batch.get(SMOOTHING_KEY)  # zeros at the root, as SmoothedActor adds them
    params = loss.qvalue_network_params.detach()
    if not _draws_masks(loss):
        params = params[:1]
    loss_actor = -_stacked_values(loss, torch.cat([observation, action], -1), params)[0].squeeze(-1)
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
