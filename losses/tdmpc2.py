"""TD-MPC2's losses (Hansen et al., 2024) as a TorchRL ``LossModule`` for stacked members.

A minibatch holds sub-episodes ``[R, B, H]`` of ``H`` consecutive transitions (``collectors.sample_sub_episodes``:
``"mask"`` marks the steps inside their episode). From the first observation the model rolls its latent state
forward through the actions taken, z_0 = h(s_0), z_(t+1) = d(z_t, a_t), and per step t, weighted rho^t:

- consistency: the mean over latent units of (z_(t+1) - h(s'_t))^2, the encoder's value of the next observation
  taken as fixed;
- reward: the cross-entropy of R(z_t, a_t)'s logits with the two-hot encoding of symlog(r_t) on the support;
- value: the same for each Q-network's Q(z_t, a_t) against the TD target r_t + gamma (1 - terminated_t)
  min_i Q~_i(h(s'_t), a'), a' the prior's action at h(s'_t) (a draw), Q~ the target networks (TorchRL's
  ``target_qvalue_network_params``, ``td.tau``), averaged over the Q-networks;
- the prior's loss, on the latent states z_0 .. z_(H-1) taken as fixed and with the Q-networks fixed (TD-MPC2
  also counts z_H):
  entropy x log pi(a|z) - Q(z, a) / S, a a reparameterised draw, Q the Q-networks' mean, S each member's
  running 5%-95% range of Q(z_0, .) (moved by ``scale_tau`` each step), at least 1.

A step after a terminated one, or outside its episode, is not part of its sub-episode: its terms count zero
(each member's loss is the mean over its B sub-episodes of the sum over steps, divided by H). The model's
parts (encoder, dynamics, reward, prior: ``learners.latent.LatentModel``) are ``actor_network_params``, the
Q-networks ``qvalue_network_params`` (TorchRL's names, so its soft update and the project's optimisers read
them as they read SAC's); the model and Q-networks minimise the first three terms weighted, the prior the last.
"""

from __future__ import annotations

from collections.abc import Sequence

import functools
from dataclasses import dataclass

import torch
from torch import nn
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from torchrl.objectives import LossModule

from losses.functional import symexp, symlog
from losses.td import DrawnTanhNormal, stacked_values

TARGET_NOISE_KEY = "tdmpc2_target_noise"  # [R, B, H, A]: the prior's draws at h(s'_t) for the TD target
PRIOR_NOISE_KEY = "tdmpc2_prior_noise"  # [R, B, H, A]: the prior's draws at z_0 .. z_(H-1) for its loss


@functools.lru_cache(maxsize=16)
def _points(v_max: float, bins: int, device: torch.device) -> torch.Tensor:
    return torch.linspace(-v_max, v_max, bins, device=device)


@dataclass(frozen=True)
class Support:
    """The categorical support of rewards and values: ``bins`` points evenly from -v_max to v_max in symlog
    space."""

    v_max: float
    bins: int

    def points(self, device=None) -> torch.Tensor:
        return _points(self.v_max, self.bins, torch.device(device) if device is not None else torch.device("cpu"))

    def value(self, logits: torch.Tensor) -> torch.Tensor:
        """The distribution's expected symlog value, back in real units: ``[..., bins] -> [..., 1]``."""
        return symexp((logits.softmax(-1) * self.points(logits.device)).sum(-1, keepdim=True))


def prior_action(model: nn.Module, z: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """The policy prior's action at latent states ``z``: tanh(loc + scale * noise), (loc, scale) from the
    model's prior head (``learners.latent.LatentModel.pi``)."""
    loc, scale = model.pi(z)
    return torch.tanh(loc + scale * noise)


def two_hot(x: torch.Tensor, support: Support) -> torch.Tensor:
    """symlog(x) ``[..., 1]`` as a distribution on the support ``[..., bins]``: its mass split between the two
    points around it in proportion to its closeness to each (clipped to the support's range)."""
    step = 2 * support.v_max / (support.bins - 1)
    position = (symlog(x).clamp(-support.v_max, support.v_max) + support.v_max) / step
    lower = position.floor().clamp(0, support.bins - 1)
    upper = (lower + 1).clamp(max=support.bins - 1)
    fraction = position - lower
    out = torch.zeros(*x.shape[:-1], support.bins, dtype=x.dtype, device=x.device)
    out.scatter_(-1, lower.long(), 1 - fraction)
    return out.scatter_add_(-1, upper.long(), fraction)


def cross_entropy(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """-sum_k target_k log softmax(logits)_k over the last dimension."""
    return -(target * logits.log_softmax(-1)).sum(-1)


class TDMPC2Loss(LossModule):
    """The module's docstring. ``model`` is the members' ``LatentModel`` (trained as built: its parameters are the
    acting policy's), ``qvalue_networks`` the Q-networks Q(z, a) -> ``bins`` logits (TensorDict modules)."""

    actor_network: nn.Module  # the members' latent model (learners.latent.LatentModel)
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams
    qvalue_network: TensorDictModule
    qvalue_network_params: TensorDictParams
    target_qvalue_network_params: TensorDictParams
    out_keys = ["loss_consistency", "loss_reward", "loss_value", "loss_actor", "q_scale"]

    def __init__(self, model: nn.Module, qvalue_networks: Sequence, *, support: Support, horizon: int,
                 rho: float, consistency_weight: float, reward_weight: float, value_weight: float,
                 entropy: float, scale_tau: float, members: int, generators: Sequence[torch.Generator]):
        super().__init__()
        self.convert_to_functional(model, "actor_network")
        self.convert_to_functional(list(qvalue_networks), "qvalue_network", len(qvalue_networks),
                                   create_target_params=True)
        self.support, self.horizon, self.rho = support, horizon, rho
        self.weights = {"consistency": consistency_weight, "reward": reward_weight, "value": value_weight}
        self.entropy, self.scale_tau = entropy, scale_tau
        self.members, self.generators = members, list(generators)
        self.gamma = 0.99
        self.register_buffer("q_scale", torch.ones(members))  # S: each member's running 5%-95% range of Q

    def make_value_estimator(self, value_type=None, **hyperparams) -> None:
        """Its TD target is its own (the module's docstring); ``gamma`` is the run's discount."""
        self.gamma = float(hyperparams.get("gamma", self.gamma))

    @property
    def model(self) -> nn.Module:
        return self.actor_network

    def q_logits(self, z: torch.Tensor, action: torch.Tensor, params: TensorDictBase) -> torch.Tensor:
        """Every Q-network's logits ``[Q, R, ..., bins]`` at (z, a) ``[R, ..., L + A]`` with ``params``."""
        return stacked_values(self, torch.cat([z, action], -1), params)

    @torch.no_grad()
    def planning_value(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The Q-networks' mean value ``[R, ..., 1]`` as they stand: the planner's terminal value."""
        return self.support.value(self.q_logits(z, action, self.qvalue_network_params)).mean(0)

    def draw(self, batch: TensorDictBase) -> None:
        """The prior's draws the step reads, from each member's generator (``TARGET_NOISE_KEY``, ``PRIOR_NOISE_KEY``)."""
        members, size, horizon = batch.batch_size
        actions = batch.get("action").shape[-1]
        noise = torch.stack([torch.randn(size, 2 * horizon, actions, generator=g, device=g.device)
                             for g in self.generators])
        batch.set(TARGET_NOISE_KEY, noise[:, :, :horizon])
        batch.set(PRIOR_NOISE_KEY, noise[:, :, horizon:])

    def forward(self, batch: TensorDictBase) -> TensorDict:
        model, support = self.model, self.support
        action = batch.get("action")
        reward, terminated = batch.get(("next", "reward")), batch.get(("next", "terminated")).to(action.dtype)
        members, size, horizon = batch.batch_size
        # a step counts when it lies inside its episode and no step before it in the sub-episode ended it
        ended_before = torch.cat([torch.zeros_like(terminated[:, :, :1]), terminated[:, :, :-1]], 2)[..., 0]
        valid = batch.get("mask").to(action.dtype) * (1 - ended_before.cummax(2).values)  # [R, B, H]
        rho = self.rho ** torch.arange(horizon, dtype=action.dtype, device=action.device)

        def member_term(values: torch.Tensor, weight: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
            """[R, B, T] terms -> [R]: the mean over sub-episodes of the weighted sum over steps, / H."""
            return (values * weight * steps).sum(2).mean(1) / horizon

        with torch.no_grad():
            next_z = model.encode(batch.get(("next", "observation")))  # [R, B, H, L]
            next_action = prior_action(model, next_z, batch.get(TARGET_NOISE_KEY))
            next_value = support.value(self.q_logits(next_z, next_action, self.target_qvalue_network_params))
            target = reward + self.gamma * (1 - terminated) * next_value.min(0).values  # [R, B, H, 1]

        z = model.encode(batch.get("observation")[:, :, 0])
        latents, consistency = [z], []
        for t in range(horizon):
            z = model.next(z, action[:, :, t])
            latents.append(z)
            consistency.append((z - next_z[:, :, t]).square().mean(-1))
        consistency = torch.stack(consistency, 2)  # [R, B, H]
        rolled = torch.stack(latents[:-1], 2)  # z_0 .. z_(H-1), [R, B, H, L]
        reward_loss = cross_entropy(model.reward(torch.cat([rolled, action], -1)), two_hot(reward, support))
        value_loss = cross_entropy(self.q_logits(rolled, action, self.qvalue_network_params),
                                   two_hot(target, support)).mean(0)

        fixed = rolled.detach()
        loc, scale = model.pi(fixed)
        prior, log_prob = DrawnTanhNormal(loc, scale, batch.get(PRIOR_NOISE_KEY), low=-1.0,
                                          high=1.0).rsample_and_log_prob()
        q = support.value(self.q_logits(fixed, prior, self.qvalue_network_params.detach())).mean(0)[..., 0]
        with torch.no_grad():
            spread = torch.quantile(q[:, :, 0], torch.tensor([0.05, 0.95], dtype=q.dtype, device=q.device), dim=1)
            self.q_scale.lerp_(spread[1] - spread[0], self.scale_tau)
        steps = rho[:horizon]
        actor_loss = member_term(self.entropy * log_prob - q / self.q_scale.clamp(min=1.0).view(members, 1, 1),
                                 steps, valid)
        out = {"loss_consistency": self.weights["consistency"] * member_term(consistency, steps, valid),
               "loss_reward": self.weights["reward"] * member_term(reward_loss, steps, valid),
               "loss_value": self.weights["value"] * member_term(value_loss, steps, valid),
               "loss_actor": actor_loss, "q_scale": self.q_scale.clone()}
        return TensorDict(out, batch_size=[])
