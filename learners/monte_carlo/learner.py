"""The paper's learners in a population (the torch half of ``learners.monte_carlo``).

Networks: the paper's actor (a Gaussian policy) and Monte-Carlo critic, V(s) for PPO and
Q(s, a) for SPG, stacked over members (``learners.networks``), member r's initial weights
drawn from its own generator. Loss: ``losses.LogClipPPOLoss`` or ``losses.SPGLoss``, one value
per member. Update phase (``PhaseRunner``): ``value_epochs`` critic steps, then
``policy_epochs`` actor steps, each on one minibatch per member drawn with the member's
generator (or by priority under prioritised replay).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from collectors import ReplayMemory, sample_minibatch
from collectors.replay import member_minibatch
from collectors.returns import TRANSITION_KEYS
from learners.base import (Learner, MetricTotals, Optimisers, diverged_members, freeze_member, objective,
                           prioritised_minibatch)
from learners.compiling import compile_step
from learners.monte_carlo.fused import (FusedCritic, FusedPPOActor, FusedSPGActor, GaussianPolicyPass,
                                        actor_refusal, critic_refusal, loss_refusal)
from learners.networks import MemberNormal, MemberSampler, StackedCriticNet, StackedGaussianPolicyNet, reset_parameters
from learners.optim import MemberAdam
from learners.registry import spec as learner_spec
from learners.solo import make_actor, make_critic
from losses import LogClipPPOLoss, SPGLoss
from losses.common import PRIORITY_KEY


@dataclass
class Networks:
    actor_net: StackedGaussianPolicyNet
    critic_net: StackedCriticNet
    actor: torch.nn.Module  # ProbabilisticActor over actor_net
    critic: torch.nn.Module  # TensorDictModule over critic_net
    sampler: MemberSampler  # the acting policy: observation -> clipped sampled action


def make_networks(cfg, env, generators: list[torch.Generator]) -> Networks:
    """The members' networks, member r's initial weights drawn from ``generators[r]`` (actor
    first, then critic), Glorot-uniform kernels and zero biases."""
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    learner = learner_spec(cfg.algo.loss)
    state_action = learner.critic(cfg.algo)[2]  # Q(s, a) (SPG's) or V(s) (PPO's)
    net, members = cfg.network, len(generators)
    device = generators[0].device
    actor_net = StackedGaussianPolicyNet(members, obs_dim, action_dim, net.actor_hidden, net.activation).to(device)
    critic_net = StackedCriticNet(members, obs_dim + action_dim * state_action, net.critic_hidden,
                                  net.activation).to(device)
    reset_parameters(actor_net, generators)
    reset_parameters(critic_net, generators)
    sampler = MemberSampler(actor_net, generators, action_dim, block=cfg.env.episode_steps)
    return Networks(actor_net, critic_net, make_actor(actor_net, MemberNormal), make_critic(critic_net, state_action),
                    sampler)


def make_loss(cfg, networks: Networks, generators: list[torch.Generator]) -> LogClipPPOLoss | SPGLoss:
    """The learner's loss module (its module's ``loss``) with the family's settings, on the members' device."""
    algo = cfg.algo
    common = {"entropy_coeff": algo.entropy_coeff, "joint_log_prob": algo.joint_log_prob,
              "members": len(generators)}
    return learner_spec(algo.loss).torch_half().loss(cfg, networks, generators, common).to(generators[0].device)


def make_optimisers(cfg, networks: Networks) -> Optimisers:
    """Adam over the stacked parameters (``learners.optim.MemberAdam``: ``torch.optim.Adam``'s
    arithmetic, bit for bit): element-wise, so exactly one Adam per member."""
    algo = cfg.algo
    return Optimisers(actor=MemberAdam(networks.actor_net.parameters(), lr=algo.actor_lr, eps=algo.adam_eps),
                      critic=MemberAdam(networks.critic_net.parameters(), lr=algo.critic_lr, eps=algo.adam_eps))


FUSED = True  # the steps on plain tensors where learners.monte_carlo.fused allows (False: always the loss module)


class PhaseRunner:
    """Runs ``value_epochs`` critic steps then ``policy_epochs`` actor steps (Adam, one
    minibatch per member each, drawn with replacement from the member's data with its own
    generator), calling the loss's hooks where the protocol places them, and collects the
    loss's diagnostics per member."""

    def __init__(self, loss, optimisers, value_epochs: int, policy_epochs: int,
                 generators: list[torch.Generator], sampler=None, compiled: bool = False,
                 critic_net: torch.nn.Module | None = None, actor_net: torch.nn.Module | None = None):
        """``sampler``: a ``collectors.prioritised.ProportionalSampler`` holding the replay
        memory's priorities (prioritised replay: every minibatch is drawn by priority, the critic's
        loss weighted by importance and its errors |G - critic| become the new priorities), or None.
        ``compiled``: compile each step's objective (``learners.compiling``). ``critic_net``,
        ``actor_net``: the stacked networks; when given and ``FUSED``, the steps
        ``learners.monte_carlo.fused`` computes run there (the loss module's numbers, bit for bit)."""
        self.loss = loss
        self.optimisers = optimisers
        self.value_epochs = value_epochs
        self.policy_epochs = policy_epochs
        self.generators = list(generators)
        self.sampler = sampler
        self.active = torch.ones(len(self.generators), device=optimisers.critic.params[0].device)  # 0: frozen
        self.critic_metrics, self.actor_metrics = loss.critic_metrics, loss.actor_metrics
        if compiled:
            loss.bind_calls()
        self._critic_objective = compile_step(self._critic_step_objective, compiled)
        self.fused_critic = None
        self.fused_actor = None
        # the loss's own code or settings (a subclass, an unknown setting, an edited function): said in one line.
        # A loss of its own (a new learner's) has no fused phases: the loss module computes, nothing to say.
        # The code is read only where the fused phases could run.
        own = not isinstance(loss, (SPGLoss, LogClipPPOLoss))
        self.code_refusal = None

        def code_refusal() -> str | None:
            self.code_refusal = loss_refusal(loss)
            return self.code_refusal

        why = (("learners.monte_carlo.learner.FUSED is off" if not FUSED else None)
               or (f"{type(loss).__name__} has no fused phases (SPGLoss's and LogClipPPOLoss's have)" if own else None)
               or ("the networks were not given" if critic_net is None else None)
               or ("prioritised replay draws its minibatches by priority" if sampler is not None else None)
               or ("compile=true compiles the loss module's step" if compiled else None)
               or code_refusal() or critic_refusal(critic_net))
        actor_why = why
        if why is None:
            self.fused_critic = FusedCritic(critic_net, optimisers.critic, self.active)
            self._critic_in_keys = list(getattr(loss, loss.critic_attr).in_keys)
            actor_why = "the actor network was not given" if actor_net is None else actor_refusal(actor_net)
            if actor_why is None:
                keys = [*loss.actor_network.in_keys, loss.tensor_keys.action]
                if isinstance(loss, SPGLoss) and loss.entropy_coeff == 0:
                    self.fused_actor = FusedSPGActor(loss, GaussianPolicyPass(actor_net, optimisers.actor),
                                                     critic_net, self.active)
                    keys += self._critic_in_keys
                elif isinstance(loss, LogClipPPOLoss):
                    self.fused_actor = FusedPPOActor(loss, GaussianPolicyPass(actor_net, optimisers.actor),
                                                     self.active)
                    keys += [loss.tensor_keys.sample_log_prob, loss.tensor_keys.advantage]
                else:
                    actor_why = "SPG's entropy bonus (algo.entropy_coeff) is computed by the loss module only"
                self._actor_in_keys = list(dict.fromkeys(keys))
        if why is None or why != self.code_refusal:
            self.code_refusal = None  # said only where it is what keeps the fused steps off
        self.fast_path_code = ("learners.monte_carlo.fused.",)  # its fused phases' own code (learners.fast_paths)
        # summary.json's record of the update path (engine.runner): which computes each phase's steps and why
        self.path = {"critic": "fused" if self.fused_critic is not None else "loss module",
                     "actor": "fused" if self.fused_actor is not None else "loss module",
                     **({"why": why} if why else {}), **({"actor_why": actor_why} if actor_why and actor_why != why else {})}
        self._actor_objective = compile_step(self._actor_step_objective, compiled)

    @property
    def fused(self) -> bool:
        """Whether the phase's steps run fused (``learners.monte_carlo.fused``), the critic's at least."""
        return self.fused_critic is not None

    def _critic_step_objective(self, batch: TensorDictBase) -> tuple[torch.Tensor, dict]:
        return objective(self.loss.critic_loss(batch), self.active)

    def _actor_step_objective(self, batch: TensorDictBase) -> tuple[torch.Tensor, dict]:
        return objective(self.loss.actor_loss(batch), self.active)

    def run(self, data: TensorDictBase, minibatch_size: int, totals: "MetricTotals", episode: int = 0) -> dict[int, str]:
        """One phase on ``data`` (``[R, n]``) before or after episode ``episode`` (unused: every phase
        is alike); returns {member: reason} for members that diverged."""
        loss = self.loss
        loss.before_critic_phase(data)
        if self.fused_critic is not None:
            self._fused_critic_phase(data, minibatch_size, totals)
        for _ in range(0 if self.fused_critic is not None else self.value_epochs):
            batch, index = self._minibatch(data, minibatch_size)
            total, entries = self._critic_objective(batch)
            if index is not None:
                self.sampler.update_priority(index.cpu(), entries.pop(PRIORITY_KEY).cpu())
            self._step(self.optimisers.critic, total, entries, "critic", totals)
        loss.before_actor_phase(data)
        if self.fused_actor is not None:
            self._fused_actor_phase(data, minibatch_size, totals)
        for _ in range(0 if self.fused_actor is not None else self.policy_epochs):
            batch = self._minibatch(data, minibatch_size)[0]
            loss.draw(batch)
            total, entries = self._actor_objective(batch)
            self._step(self.optimisers.actor, total, entries, "actor", totals)
        loss.after_actor_phase()
        # Checked once per phase: a NaN or inf loss or gradient leaves non-finite parameters
        # (Adam propagates it), and one check per phase costs little per step.
        return diverged_members(self.optimisers, totals, self.active)

    def _fused_critic_phase(self, data: TensorDictBase, size: int, totals: "MetricTotals") -> None:
        """``value_epochs`` critic steps by ``FusedCritic``."""
        parts = [data.get(key) for key in self._critic_in_keys]
        tensors = {"inputs": parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1),
                   "target": data.get(self.loss.tensor_keys.value_target)}
        self._fused_steps(tensors, data.batch_size[1], self.value_epochs, size,
                          lambda batch: self.fused_critic.step(batch["inputs"], batch["target"]), "critic", totals)

    def _fused_actor_phase(self, data: TensorDictBase, size: int, totals: "MetricTotals") -> None:
        """``policy_epochs`` actor steps by the fused actor."""
        tensors = {key: data.get(key) for key in self._actor_in_keys}
        self._fused_steps(tensors, data.batch_size[1], self.policy_epochs, size, self.fused_actor.step, "actor", totals)

    def _fused_steps(self, tensors: dict, n: int, steps: int, size: int, step, prefix: str,
                     totals: "MetricTotals") -> None:
        """``steps`` fused steps, each on a minibatch of ``tensors`` (``[R, n, ...]``) drawn as
        ``sample_minibatch`` draws it (the same indices from the same generators)."""
        for _ in range(steps):
            totals.add(prefix, step(member_minibatch(tensors, n, size, self.generators)))

    def _minibatch(self, data: TensorDictBase, size: int) -> tuple[TensorDictBase, torch.Tensor | None]:
        """A minibatch per member, uniform (and no index) or by priority (with its slot indices)."""
        if self.sampler is None:
            return sample_minibatch(data, size, self.generators), None
        return prioritised_minibatch(data, size, self.generators, self.sampler)

    def _step(self, optimiser, total: torch.Tensor, entries: dict, prefix: str, totals: "MetricTotals") -> None:
        optimiser.zero_grad(set_to_none=True)
        total.backward()
        optimiser.step()
        totals.add(prefix, entries)

    @torch.no_grad()
    def freeze(self, member: int) -> None:
        """Stop training ``member``: zero its parameters and Adam moments, mask its loss terms.

        With zero gradient, zero moments and zero weights, Adam leaves it at zero; its
        networks stay finite (its car keeps driving, unrecorded) and cost the others nothing.
        """
        self.active[member] = 0.0
        freeze_member(self.optimisers, member)


def build(cfg, env, generators: list[torch.Generator], memory: ReplayMemory) -> Learner:
    """Networks, loss, optimisers and update phase of ``cfg.algo`` (loss ppo or spg) for one
    member per generator."""
    networks = make_networks(cfg, env, generators)
    loss = make_loss(cfg, networks, generators)
    optimisers = make_optimisers(cfg, networks)
    phases = PhaseRunner(loss, optimisers, cfg.algo.value_epochs, cfg.algo.policy_epochs, generators,
                         sampler=memory.sampler, compiled=cfg.compile, critic_net=networks.critic_net,
                         actor_net=networks.actor_net)
    return Learner(networks, loss, optimisers, memory, phases,
                   TRANSITION_KEYS, monte_carlo=True)
