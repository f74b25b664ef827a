"""A training run's pieces, from a validated ``RunConfig``: ``build(cfg, seeds)``.

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

import learners
from collectors import ReplayMemory, ReplaySchedule, make_collector
from engine.config import ConfigError, RunConfig
from engine.start import start_actors
from learners.base import Learner
from racing.torchrl_env import RacingTorchEnv


@dataclass
class Run:
    """What a population trains with; the collector comes later (``make_episode_collector``),
    once a checkpoint has said how many episodes remain."""

    generators: list[torch.Generator]  # one per member: everything random on the torch side
    env: RacingTorchEnv  # one car per member
    learner: Learner  # networks, acting policy, loss, optimisers, replay memory, update phase
    schedule: ReplaySchedule  # when to train on memory and on recent experience
    minibatch_size: int  # per member, after the er mode's fraction
    starts: list[dict] | None = None  # algo.td.start_from: what each member's actor started from (summary.json)


def build(cfg: RunConfig, seeds: tuple[int, ...]) -> Run:
    """Seed, then the members' generators, cars, learner (``learners.<family>.build``) and schedule."""
    # Every learner draws only from the members' generators; the global generators are seeded
    # anyway (with the first member's seed), so that nothing left to them varies run to run.
    seed_everything(seeds[0])
    generators = make_generators(seeds, cfg.device)
    env = make_env(cfg, seeds)
    starts = start_actors(cfg, seeds)  # algo.td.start_from: another run's actor per member (engine.start)
    learner = make_learner(cfg, env, generators, starts)
    schedule = make_schedule(cfg)
    return Run(generators, env, learner, schedule, schedule.minibatch_size(cfg.algo.minibatch_size),
               [start["record"] for start in starts] if starts else None)


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
    """One car per member: on the member's track (``env.track=fixed``), on a new random track
    per episode (``random``) or on the file's track (``file``); car r's random stream is seeded
    with ``seeds[r]``."""
    td = getattr(cfg.algo, "td", None)  # what an off-policy learner's Q-networks read besides (s, a)
    extra = {"privileged": bool(getattr(td, "privileged_critic", False)), "history": getattr(td, "critic_history", 0),
             "past_steps": cfg.env.past_steps}
    if cfg.env.track == "file":
        env = RacingTorchEnv(len(seeds), track_file=cfg.env.track_file, track_scale=cfg.env.track_scale,
                             track_closed=cfg.env.track_closed, device=cfg.device, nearest_ray=cfg.env.nearest_ray,
                             **extra, **cfg.env.options)
    else:
        track_seeds = list(seeds) if cfg.env.track == "fixed" else [None] * len(seeds)
        env = RacingTorchEnv(len(seeds), track_seeds=track_seeds, device=cfg.device,
                             nearest_ray=cfg.env.nearest_ray, **extra, **cfg.env.options)
    env.sim.seed(list(seeds))
    return env


# -------------------------------------------------------------------------------- learner
def make_learner(cfg: RunConfig, env: RacingTorchEnv, generators: list[torch.Generator],
                 starts: list[dict] | None = None) -> Learner:
    """The replay memory, then the learner family's networks, loss, optimisers and update phase; ``starts``
    (``engine.start.start_actors``): the members' actors start from other runs' weights."""
    memory = ReplayMemory(cfg.er.buffer_size, members=len(generators), device=cfg.device, priority=cfg.er.priority)
    if starts is None:
        return learners.family(cfg.algo.loss).build(cfg, env, generators, memory)
    try:
        return learners.family(cfg.algo.loss).build(cfg, env, generators, memory, starts=starts)
    except ValueError as err:  # a start whose networks are not this run's (the learner names its option)
        raise ConfigError(str(err)) from None


# ------------------------------------------------------------------------------ collector
def make_episode_collector(cfg: RunConfig, env: RacingTorchEnv, sampler, episodes: int):
    """Both backends act with the learner's sampler (the TorchRL ``Collector`` through
    ``collectors.ActingPolicy``), so they draw the same actions. The ``Collector`` calls its policy
    once when it is built, to see what it writes: that call must not draw noise."""
    with sampler.paused():
        return make_collector(cfg.env.collector, env, sample=sampler, steps=cfg.env.episode_steps,
                              episodes=episodes)


def make_schedule(cfg: RunConfig) -> ReplaySchedule:
    er = cfg.er
    return ReplaySchedule(er.name, er.train_on_memory, er.train_on_recent, er.minibatch_fraction)
