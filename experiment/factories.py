"""``make_*`` factories: from a validated ``RunConfig`` to the pieces of a training run."""

from __future__ import annotations

import random
from dataclasses import dataclass

import numpy as np
import torch

from collectors import ReplaySchedule, make_collector
from experiment.config import RunConfig
from experiment.models import (CriticNet, GaussianPolicyNet, make_actor, make_critic, make_policy,
                               make_sampler)
from losses import LogClipPPOLoss, SPGLoss
from racing.torchrl_env import RacingTorchEnv


def seed_everything(seed: int) -> None:
    """Seed torch's, NumPy's and Python's global generators (workers may be reused: call per run)."""
    torch.manual_seed(seed)
    np.random.seed(seed % 2**32)
    random.seed(seed)


# ---------------------------------------------------------------------------- environment
def make_env(cfg: RunConfig) -> RacingTorchEnv:
    """One car on the run's track (``env.track=fixed``) or on a new random track per episode."""
    track_seeds = [cfg.seed] if cfg.env.track == "fixed" else None
    env = RacingTorchEnv(1, track_seeds=track_seeds, nearest_ray=cfg.env.nearest_ray, **cfg.env.options)
    env.set_seed(cfg.seed)
    return env


# -------------------------------------------------------------------------------- models
@dataclass
class Models:
    actor_net: GaussianPolicyNet
    critic_net: CriticNet
    actor: torch.nn.Module  # ProbabilisticActor over actor_net
    critic: torch.nn.Module  # TensorDictModule over critic_net


def make_models(cfg: RunConfig, env: RacingTorchEnv) -> Models:
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    state_action = cfg.algo.loss == "spg"
    net = cfg.network
    actor_net = GaussianPolicyNet(obs_dim, action_dim, net.actor_hidden, net.activation)
    critic_net = CriticNet(obs_dim + action_dim * state_action, net.critic_hidden, net.activation)
    return Models(actor_net, critic_net, make_actor(actor_net), make_critic(critic_net, state_action))


# ------------------------------------------------------------------------------ collector
def make_episode_collector(cfg: RunConfig, env: RacingTorchEnv, models: Models, episodes: int):
    return make_collector(cfg.env.collector, env, policy=make_policy(models.actor),
                          sample=make_sampler(models.actor_net), steps=cfg.env.episode_steps,
                          episodes=episodes)


def make_schedule(cfg: RunConfig) -> ReplaySchedule:
    er = cfg.er
    return ReplaySchedule(er.name, er.train_on_memory, er.train_on_recent, er.minibatch_fraction)


# ----------------------------------------------------------------------------------- loss
def make_loss(cfg: RunConfig, models: Models) -> LogClipPPOLoss | SPGLoss:
    algo = cfg.algo
    common = {"entropy_coeff": algo.entropy_coeff, "joint_log_prob": algo.joint_log_prob}
    if algo.loss == "ppo":
        return LogClipPPOLoss(models.actor, models.critic, clip_epsilon=algo.ppo.clip_epsilon,
                              ratio_space=algo.ppo.ratio_space, **common)
    spg = algo.spg
    return SPGLoss(models.actor, models.critic, num_samples=spg.num_samples, temperature=spg.temperature,
                   temperature_decay=spg.temperature_decay, prioritised=spg.prioritised,
                   sample_around=spg.sample_around, baseline=spg.baseline, **common)


# ------------------------------------------------------------------------------ optimisers
@dataclass
class Optimisers:
    actor: torch.optim.Adam
    critic: torch.optim.Adam


def make_optimisers(cfg: RunConfig, models: Models) -> Optimisers:
    algo = cfg.algo
    return Optimisers(
        actor=torch.optim.Adam(models.actor_net.parameters(), lr=algo.actor_lr, eps=algo.adam_eps, fused=True),
        critic=torch.optim.Adam(models.critic_net.parameters(), lr=algo.critic_lr, eps=algo.adam_eps,
                                fused=True),
    )
