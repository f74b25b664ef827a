"""``make_*`` factories: from a validated ``RunConfig`` to the pieces of a training run.

A run trains a population: one member per seed of ``cfg.members`` (one for a solo run), each
with its own car (on its own track and random stream), its own networks (stacked parameters)
and its own ``torch.Generator`` for everything random on the torch side (initial weights,
action noise, minibatch indices, SPG's perturbations). So a member's run depends on its seed
alone, not on the other members or their order.
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np
import torch

from collectors import ReplayMemory, ReplaySchedule, make_collector
from collectors.returns import TRANSITION_KEYS
from experiment.config import RunConfig
from experiment.models import make_actor, make_critic
from experiment.optim import MemberAdam
from experiment.phases import PhaseRunner
from experiment.stacked import (MemberNormal, MemberSampler, StackedCriticNet, StackedGaussianPolicyNet,
                                member_state_dict, reset_parameters)
from losses import LogClipPPOLoss, SPGLoss
from racing.torchrl_env import RacingTorchEnv


def seed_everything(seed: int) -> None:
    """Seed torch's, NumPy's and Python's global generators (workers may be reused: call per run).

    Training draws from the members' own generators (``make_generators``); the global ones are
    seeded only so that nothing else can make two runs differ."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


def make_generators(seeds: tuple[int, ...], device: str = "cpu") -> list[torch.Generator]:
    """One ``torch.Generator`` per member (on ``device``), seeded with the member's seed."""
    return [torch.Generator(device=device).manual_seed(seed) for seed in seeds]


# ---------------------------------------------------------------------------- environment
def make_env(cfg: RunConfig, seeds: tuple[int, ...]) -> RacingTorchEnv:
    """One car per member: on the member's track (``env.track=fixed``) or on a new random track
    per episode; car r's random stream is seeded with ``seeds[r]``."""
    track_seeds = list(seeds) if cfg.env.track == "fixed" else [None] * len(seeds)
    env = RacingTorchEnv(len(seeds), track_seeds=track_seeds, device=cfg.device, nearest_ray=cfg.env.nearest_ray,
                         **cfg.env.options)
    env.sim.seed(list(seeds))
    return env


# -------------------------------------------------------------------------------- models
@dataclass
class Models:
    actor_net: StackedGaussianPolicyNet
    critic_net: StackedCriticNet
    actor: torch.nn.Module  # ProbabilisticActor over actor_net
    critic: torch.nn.Module  # TensorDictModule over critic_net
    sampler: MemberSampler  # the acting policy: observation -> clipped sampled action


def make_models(cfg: RunConfig, env: RacingTorchEnv, generators: list[torch.Generator]) -> Models:
    """The members' networks, member r's initial weights drawn from ``generators[r]`` (actor
    first, then critic), Glorot-uniform kernels and zero biases."""
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    state_action = cfg.algo.loss == "spg"
    net, members = cfg.network, len(generators)
    device = generators[0].device
    actor_net = StackedGaussianPolicyNet(members, obs_dim, action_dim, net.actor_hidden, net.activation).to(device)
    critic_net = StackedCriticNet(members, obs_dim + action_dim * state_action, net.critic_hidden,
                                  net.activation).to(device)
    reset_parameters(actor_net, generators)
    reset_parameters(critic_net, generators)
    sampler = MemberSampler(actor_net, generators, action_dim, block=cfg.env.episode_steps)
    return Models(actor_net, critic_net, make_actor(actor_net, MemberNormal), make_critic(critic_net, state_action),
                  sampler)


# ------------------------------------------------------------------------------ collector
def make_episode_collector(cfg: RunConfig, env: RacingTorchEnv, models: Models, episodes: int):
    """Both backends act with the same sampler (the TorchRL ``Collector`` through a
    ``TensorDictModule``), so they draw the same actions. The ``Collector`` calls its policy
    once when it is built, to see what it writes: that call must not draw noise."""
    from tensordict.nn import TensorDictModule

    policy = TensorDictModule(models.sampler, in_keys=["observation"], out_keys=["action"])
    with models.sampler.paused():
        return make_collector(cfg.env.collector, env, policy=policy, sample=models.sampler,
                              steps=cfg.env.episode_steps, episodes=episodes)


def make_schedule(cfg: RunConfig) -> ReplaySchedule:
    er = cfg.er
    return ReplaySchedule(er.name, er.train_on_memory, er.train_on_recent, er.minibatch_fraction)


# ----------------------------------------------------------------------------------- loss
def make_loss(cfg: RunConfig, models: Models, generators: list[torch.Generator]) -> LogClipPPOLoss | SPGLoss:
    algo = cfg.algo
    common = {"entropy_coeff": algo.entropy_coeff, "joint_log_prob": algo.joint_log_prob,
              "members": len(generators)}
    if algo.loss == "ppo":
        return LogClipPPOLoss(models.actor, models.critic, clip_epsilon=algo.ppo.clip_epsilon,
                              ratio_space=algo.ppo.ratio_space, **common).to(generators[0].device)
    spg = algo.spg
    loss = SPGLoss(models.actor, models.critic, num_samples=spg.num_samples, temperature=spg.temperature,
                   temperature_decay=spg.temperature_decay, prioritised=spg.prioritised,
                   sample_around=spg.sample_around, baseline=spg.baseline, **common)
    loss.set_generators(generators)
    return loss.to(generators[0].device)


# ------------------------------------------------------------------------------ optimisers
@dataclass
class Optimisers:
    actor: MemberAdam
    critic: MemberAdam


def make_optimisers(cfg: RunConfig, models: Models) -> Optimisers:
    """Adam over the stacked parameters (``experiment.optim.MemberAdam``: ``torch.optim.Adam``'s
    arithmetic, bit for bit): element-wise, so exactly one Adam per member."""
    algo = cfg.algo
    return Optimisers(actor=MemberAdam(models.actor_net.parameters(), lr=algo.actor_lr, eps=algo.adam_eps),
                      critic=MemberAdam(models.critic_net.parameters(), lr=algo.critic_lr, eps=algo.adam_eps))


# ------------------------------------------------------------------------- everything at once
@dataclass
class Training:
    """What the runner trains with, for either family of algorithms."""

    models: object  # Models or experiment.offpolicy.OffPolicyModels (actor_net, critic_net, sampler)
    loss: torch.nn.Module
    optimisers: object  # .actor and .critic MemberAdam
    memory: ReplayMemory
    phases: object  # PhaseRunner or experiment.offpolicy.TDPhaseRunner
    transition_keys: tuple  # what the replay memory keeps of each step
    monte_carlo: bool  # the memory's transitions carry Monte-Carlo returns (the paper's protocol)

    def member_weights(self, member: int) -> dict[str, dict[str, torch.Tensor]]:
        """Member ``member``'s trained weights, {"actor": ..., "critic": ...}, on the CPU."""
        critic = (self.phases.member_critic(member) if hasattr(self.phases, "member_critic")  # TorchRL's Q ensemble
                  else member_state_dict(self.models.critic_net, member))
        return {"actor": member_state_dict(self.models.actor_net, member), "critic": critic}

    def state_parts(self) -> dict:
        """The stateful parts a checkpoint saves, by name."""
        parts = {"loss": self.loss, "actor_optim": self.optimisers.actor, "critic_optim": self.optimisers.critic,
                 "memory": self.memory}
        if hasattr(self.models.sampler, "state_dict"):
            parts["sampler"] = self.models.sampler
        return parts


def make_training(cfg: RunConfig, env: RacingTorchEnv, generators: list[torch.Generator]) -> Training:
    """Networks, loss, optimisers, replay memory and update schedule of ``cfg.algo``: the paper's
    protocol (ppo, spg) or TorchRL's off-policy losses (sac, td3, ``experiment.offpolicy``)."""
    members = len(generators)
    memory = ReplayMemory(cfg.er.buffer_size, members=members, device=cfg.device, priority=cfg.er.priority)
    if cfg.algo.bootstrapped:
        from experiment import offpolicy

        models = offpolicy.make_offpolicy_models(cfg, env, generators)
        loss = offpolicy.make_offpolicy_loss(cfg, models, members, env.action_spec.shape[-1])
        optimisers = offpolicy.make_offpolicy_optimisers(cfg, loss)
        phases = offpolicy.TDPhaseRunner(cfg, loss, optimisers, generators, memory if cfg.er.priority else None)
        return Training(models, loss, optimisers, memory, phases, offpolicy.TD_TRANSITION_KEYS, False)
    models = make_models(cfg, env, generators)
    loss = make_loss(cfg, models, generators)
    optimisers = make_optimisers(cfg, models)
    phases = PhaseRunner(loss, optimisers, cfg.algo.value_epochs, cfg.algo.policy_epochs, generators,
                         sampler=memory.sampler)
    return Training(models, loss, optimisers, memory, phases, TRANSITION_KEYS, True)
