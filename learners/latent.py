"""A latent model that plans (TD-MPC2's pieces, Hansen et al., 2024) for stacked members, and its planner.

``LatentModel``: an encoder h(s) -> z, latent dynamics d(z, a) -> z', a reward head R(z, a) and a policy prior
pi(z), each a stacked MLP with layer-normalised hidden layers (``learners.networks``); latent states are
simplicial: their entries in groups of ``group`` each sum to one (``simnorm``). Its ``forward`` is the prior's
Gaussian at h(s), ``(loc, scale)``: what an actor of the off-policy learners outputs, so the model is saved,
normalised and evaluated as their actors are. Its Q-networks Q(z, a) are the loss's ensemble (TorchRL's layout,
``losses.tdmpc2``). Rewards and values are categorical over a support in symlog space (``symlog``).

``plan``: MPPI over ``horizon`` actions per member, the prior's trajectories among the samples, the previous
step's plan as the warm start; ``PlanningSampler``: the acting policy that plans at every step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from learners.networks import MemberNormalParamExtractor, StackedCriticNet
from learners.td.learner import OffPolicySampler
from losses.functional import per_member
from losses.tdmpc2 import Support, prior_action


def simnorm(x: torch.Tensor, group: int) -> torch.Tensor:
    """Each ``group`` consecutive features of ``x`` ``[R, ..., F]`` made a softmax (TD-MPC2's SimNorm)."""
    shape = x.shape
    return per_member(lambda t: t.reshape(*t.shape[:-1], -1, group).softmax(-1).reshape(t.shape),
                      x.reshape(shape[0], -1, group)).reshape(shape)


class LatentModel(nn.Module):
    """The members' encoder, latent dynamics, reward head and policy prior (the module's docstring).

    ``latent`` units in groups of ``group``; each part is an MLP with one hidden layer of ``width`` units
    (Linear -> layer norm -> ``activation``); the reward head outputs ``bins`` logits."""

    def __init__(self, members: int, obs_dim: int, action_dim: int, latent: int, width: int, bins: int,
                 group: int = 8, activation: str = "elu"):
        super().__init__()
        if latent % group:
            raise ValueError(f"the latent state's {latent} units must be groups of {group}")
        self.group, self.action_dim = group, action_dim

        def mlp(inputs: int, outputs: int) -> nn.Module:
            return StackedCriticNet(members, inputs, [width], activation, outputs=outputs, layer_norm=True)

        self.encoder = mlp(obs_dim, latent)
        self.dynamics = mlp(latent + action_dim, latent)
        self.reward = mlp(latent + action_dim, bins)
        self.pi = nn.Sequential(mlp(latent, 2 * action_dim),
                                MemberNormalParamExtractor(scale_lb=1e-4))

    def encode(self, observation: torch.Tensor) -> torch.Tensor:
        return simnorm(self.encoder(observation), self.group)

    def next(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        return simnorm(self.dynamics(torch.cat([z, action], -1)), self.group)

    def step(self, z: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(the reward head's logits, the next latent state) at (z, a), from one concatenation."""
        za = torch.cat([z, action], -1)
        return self.reward(za), simnorm(self.dynamics(za), self.group)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The prior's Gaussian (loc, scale) at the encoded observation (its action: tanh of a draw)."""
        return self.pi(self.encode(observation))


@dataclass(frozen=True)
class PlanOptions:
    """MPPI's settings (``algo.tdmpc2``)."""

    horizon: int
    samples: int  # trajectories per iteration, the prior's among them
    policy_samples: int  # of which drawn from the prior
    elites: int
    iterations: int
    temperature: float
    min_std: float
    max_std: float
    gamma: float

    def draws_per_step(self, action_dim: int) -> int:
        """N(0, 1) draws one planned step takes per member (``split_draws``)."""
        h, p, n, a, i = self.horizon, self.policy_samples, self.samples, action_dim, self.iterations
        return h * p * a + i * (n - p) * h * a + i * n * a + a


def split_draws(draws: torch.Tensor, options: PlanOptions, action_dim: int) -> dict[str, torch.Tensor]:
    """One step's N(0, 1) draws ``[R, draws_per_step]`` as the planner reads them: the prior's trajectories
    ``[R, H, P, A]``, the sampled actions ``[R, I, N - P, H, A]``, the prior's terminal actions ``[R, I, N, A]``,
    the executed action's noise ``[R, A]``."""
    h, p, n, a, i = options.horizon, options.policy_samples, options.samples, action_dim, options.iterations
    sizes = {"prior": (h, p, a), "samples": (i, n - p, h, a), "terminal": (i, n, a), "action": (a,)}
    out, start = {}, 0
    for key, shape in sizes.items():
        count = 1
        for s in shape:
            count *= s
        out[key] = draws[:, start:start + count].reshape(draws.shape[0], *shape)
        start += count
    return out


def trajectory_values(model: LatentModel, q_value, z: torch.Tensor, actions: torch.Tensor, terminal: torch.Tensor,
                      support: Support, gamma: float) -> torch.Tensor:
    """Each trajectory's value ``[R, N]``: from latent states ``z`` ``[R, N, L]``, the discounted predicted rewards
    of ``actions`` ``[R, N, H, A]`` then gamma^H x ``q_value`` (z_H, the prior's action with noise ``terminal``)."""
    total, discount = torch.zeros(z.shape[:-1], device=z.device), 1.0
    for t in range(actions.shape[2]):
        logits, z = model.step(z, actions[:, :, t])
        total = total + discount * support.value(logits)[..., 0]
        discount *= gamma
    final = prior_action(model, z, terminal)
    return total + discount * q_value(z, final)[..., 0]


def plan(model: LatentModel, q_value, z: torch.Tensor, mean: torch.Tensor, draws: dict[str, torch.Tensor],
         uniform: torch.Tensor, options: PlanOptions, support: Support,
         noisy: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """MPPI for each member from its latent state ``z`` ``[R, L]``: (the action ``[R, A]``, the plan's mean
    ``[R, H, A]``).

    ``mean`` is the warm start (the previous step's plan moved one step on; zeros at an episode's start);
    the standard deviation starts at ``max_std``. The prior's ``policy_samples`` trajectories (its draws rolled
    through the dynamics) join ``samples - policy_samples`` Gaussian ones; each iteration scores every
    trajectory (``trajectory_values``), keeps the ``elites`` best, weights them by exp(temperature x (value -
    best)) and refits the mean and standard deviation (clipped to [min_std, max_std]) to them. The action: the
    first of an elite chosen with probability its weight (``uniform`` ``[R]`` in [0, 1)), plus the first step's
    standard deviation x the ``"action"`` draw when ``noisy``; in [-1, 1]."""
    members, latent = z.shape
    h, p, n, k = options.horizon, options.policy_samples, options.samples, options.elites
    action_dim = mean.shape[-1]
    pi_actions = z.new_zeros(members, 0, h, action_dim)
    if p:  # the prior's trajectories, rolled through the dynamics
        state, rolled = z.unsqueeze(1).expand(members, p, latent), []
        for t in range(h):
            action = prior_action(model, state, draws["prior"][:, t])
            rolled.append(action)
            if t < h - 1:
                state = model.next(state, action)
        pi_actions = torch.stack(rolled, 2)
    start = z.unsqueeze(1).expand(members, n, latent)
    std = torch.full_like(mean, options.max_std)
    for i in range(options.iterations):
        sampled = (mean.unsqueeze(1) + std.unsqueeze(1) * draws["samples"][:, i]).clamp(-1.0, 1.0)
        actions = torch.cat([pi_actions, sampled], 1)  # [R, N, H, A]
        value = trajectory_values(model, q_value, start, actions, draws["terminal"][:, i], support, options.gamma)
        elite_value, index = value.topk(k, dim=1)  # [R, K]
        elites = actions.gather(1, index.view(members, k, 1, 1).expand(members, k, h, action_dim))
        score = per_member(torch.exp, options.temperature * (elite_value - elite_value[:, :1]))
        score = score / score.sum(1, keepdim=True)
        weight = score.view(members, k, 1, 1)
        mean = (weight * elites).sum(1)
        std = (weight * (elites - mean.unsqueeze(1)).square()).sum(1).sqrt().clamp(options.min_std, options.max_std)
    chosen = torch.searchsorted(score.cumsum(1), uniform.reshape(members, 1).to(score.dtype).contiguous()).clamp(max=k - 1)
    action = elites[torch.arange(members, device=z.device), chosen[:, 0], 0]
    if noisy:
        action = action + std[:, 0] * draws["action"]
    return action.clamp(-1.0, 1.0), mean


def shifted(mean: torch.Tensor) -> torch.Tensor:
    """The warm start for the next step: the plan moved one step on, its last step zero."""
    return torch.cat([mean[:, 1:], torch.zeros_like(mean[:, :1])], 1)


class PlanningSampler(OffPolicySampler):
    """The acting policy of a planning population, ``[R, obs] -> [R, A]``: uniform random actions for the
    first ``warmup_blocks`` episodes (``OffPolicySampler``'s), then ``learners.latent.plan`` at every step
    with the model and ``q_value`` as they stand, the previous step's plan as the warm start (none at an
    episode's start: what is saved between episodes is ``OffPolicySampler``'s). Member r's draws come from
    ``generators[r]``, an episode (``block`` steps) at a time. Paused (a probe), the prior's tanh(loc)."""

    @classmethod
    def wrap(cls, base: OffPolicySampler, q_value, options, support) -> "PlanningSampler":
        sampler = cls(base.net, base.generators, base.action_dim, base.block, base.warmup_blocks, norm=base.norm)
        sampler.q_value, sampler.options, sampler.support = q_value, options, support
        sampler._uniform, sampler._mean = None, None
        return sampler

    def draw_block(self) -> None:
        """An episode's draws per member: uniform actions in the warm-up (``OffPolicySampler``'s), else every
        step's N(0, 1) draws for ``plan`` (``PlanOptions.draws_per_step``) and its uniform draw; the plan
        restarts."""
        if self._warmup:
            super().draw_block()
            return
        count = self.options.draws_per_step(self.action_dim)
        draws, uniform = [], []
        for g in self.generators:
            draws.append(torch.randn(self.block, count, generator=g, device=g.device))
            uniform.append(torch.rand(self.block, generator=g, device=g.device))
        self._draws, self._uniform, self._mean = torch.stack(draws), torch.stack(uniform), None

    def act(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        if self._mean is None:
            self._mean = observation.new_zeros(observation.shape[0], self.options.horizon, self.action_dim)
        action, mean = plan(self.net, self.q_value, self.net.encode(observation), self._mean,
                            split_draws(self._draws[:, step], self.options, self.action_dim),
                            self._uniform[:, step], self.options, self.support)
        self._mean = shifted(mean)
        return action


class PlanningActor(nn.Module):
    """A planning run's deterministic policy for evaluation, ``[1, N, obs] -> [1, N, A]`` (a population of one, as
    ``engine.evaluation.Policy`` calls its off-policy actors): ``plan`` with the saved model (``net``: the
    ``LatentModel``, behind its observation statistics where it kept them) and Q-networks (``qvalues``: the run's
    Q-networks stacked on the first dimension), without the executed action's noise. Its draws come from a
    generator seeded 0 at every episode's start (``reset``), so an episode from the same start drives the same
    actions; the plan carries over from step to step within an episode when one observation comes at a time
    (several at once: each planned alone, from no warm start)."""

    def __init__(self, net: nn.Module, qvalues: nn.Module, options: PlanOptions, support: Support):
        super().__init__()
        self.net, self.qvalues, self.options, self.support = net, qvalues, options, support
        self.reset()

    @property
    def model(self) -> LatentModel:
        return getattr(self.net, "net", self.net)

    def reset(self) -> None:
        self._generator = torch.Generator().manual_seed(0)
        self._mean: torch.Tensor | None = None

    def q_value(self, z: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The Q-networks' mean value ``[1, ..., 1]`` at (z, a) ``[1, ..., L + A]``."""
        x = torch.cat([z, action], -1)
        critics = self.qvalues.net.layers[0].weight.shape[0]
        return self.support.value(self.qvalues(x.expand(critics, *x.shape[1:]))).mean(0, keepdim=True)

    @torch.no_grad()
    def forward(self, observations: torch.Tensor) -> torch.Tensor:
        norm = getattr(self.net, "norm", None)
        rows = norm(observations) if norm is not None else observations
        actions, single = [], rows.shape[1] == 1
        action_dim = self.model.action_dim
        for n in range(rows.shape[1]):
            mean = self._mean if single and self._mean is not None else rows.new_zeros(1, self.options.horizon,
                                                                                        action_dim)
            draws = torch.randn(1, self.options.draws_per_step(action_dim), generator=self._generator)
            uniform = torch.rand(1, generator=self._generator)
            action, mean = plan(self.model, self.q_value, self.model.encode(rows[:, n]), mean,
                                split_draws(draws, self.options, action_dim), uniform, self.options, self.support,
                                noisy=False)
            if single:
                self._mean = shifted(mean)
            actions.append(action)
        return torch.stack(actions, 1)
