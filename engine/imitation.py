"""The reactive ceiling: how well an actor network that sees only the observation (five rays and
the speed) drives when it learns from the oracle itself, by DAgger (Ross et al., 2011).

Per track: round 0 lets the oracle drive ``episodes`` episodes and records (observation, the
oracle's action); every later round lets the current network drive (deterministically) and has
the oracle label every state it visits, planning from that state (``racing.oracle.Oracle.act``);
the data of all rounds is aggregated and the network refit from scratch by regression (mean
squared error on the action) after each round. Data episodes start from seeds 1000 + k, the
scoring protocol's episodes from seeds 0-4 (``engine.benchmark``'s: five deterministic episodes,
their mean total reward), so no scored start state is ever labelled. The network is the paper's
actor body (``learners.solo.GaussianPolicyNet``: tanh hidden layers, the Gaussian's mean as the
action) at any width.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

DATA_SEED = 1000  # data episodes start from seeds DATA_SEED + k; scored episodes from 0-4
LABELS = ("best", "mean")


@dataclass(frozen=True)
class DaggerSettings:
    rounds: int = 4  # after round 0 (the oracle's own episodes)
    episodes: int = 5  # per round
    hidden: tuple[int, ...] = (100,)
    epochs: int = 300  # passes over the aggregated data per refit
    minibatch: int = 256
    lr: float = 1e-3
    seed: int = 0
    label: str = "best"  # best: the oracle's action (its best plan's first step); mean: its last elite mean's

    def __post_init__(self) -> None:
        for name in ("episodes", "epochs", "minibatch"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.rounds < 0 or not self.hidden or min(self.hidden) < 1 or not self.lr > 0:
            raise ValueError("rounds must be >= 0, hidden a non-empty list of positive sizes and lr > 0")
        if self.label not in LABELS:
            raise ValueError(f"label must be one of {LABELS}, got {self.label!r}")


@dataclass
class DaggerResult:
    track: int
    scores: list[float] = field(default_factory=list)  # the network's protocol score after each round
    samples: list[int] = field(default_factory=list)  # aggregated (observation, action) pairs per round
    fit_error: list[float] = field(default_factory=list)  # the network's mean squared error on its data per round
    seconds: float = 0.0


def fit(observations: np.ndarray, actions: np.ndarray, settings: DaggerSettings, obs_size: int):
    """A fresh network regressed onto the data (its mean head onto the actions)."""
    from learners.solo import GaussianPolicyNet

    generator = torch.Generator().manual_seed(settings.seed)
    torch.manual_seed(settings.seed)
    net = GaussianPolicyNet(obs_size, 2, list(settings.hidden), "tanh")
    optimiser = torch.optim.Adam(net.parameters(), lr=settings.lr)
    x = torch.as_tensor(observations, dtype=torch.float32)
    y = torch.as_tensor(np.clip(actions, -1.0, 1.0), dtype=torch.float32)
    for _ in range(settings.epochs):
        order = torch.randperm(len(x), generator=generator)
        for start in range(0, len(x), settings.minibatch):
            rows = order[start:start + settings.minibatch]
            loc, _ = net(x[rows])
            loss = ((loc - y[rows]) ** 2).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    return net


def fit_error(net, observations: np.ndarray, actions: np.ndarray) -> float:
    """The network's mean squared error on (observation, action) pairs (actions clipped as ``fit``
    trains on them): how far the pupil is from its labels where it has data."""
    with torch.no_grad():
        loc, _ = net(torch.as_tensor(observations, dtype=torch.float32))
        target = torch.as_tensor(np.clip(actions, -1.0, 1.0), dtype=torch.float32)
        return float(((loc - target) ** 2).mean())


def dagger(track: int, settings: DaggerSettings = DaggerSettings(), oracle_settings=None) -> DaggerResult:
    """DAgger on one track (see the module docstring); the scores are the protocol's."""
    from engine.benchmark import Agent, score
    from engine.evaluation import Policy
    from racing.gym_env import RacingEnv
    from racing.oracle import Oracle, OracleSettings

    start = time.perf_counter()
    env = RacingEnv(track_seed=track)
    oracle = Oracle(env.config, oracle_settings or OracleSettings(), seed=settings.seed)
    observations: list[np.ndarray] = []
    actions: list[np.ndarray] = []
    result = DaggerResult(track)
    policy = None
    for round_ in range(settings.rounds + 1):
        for k in range(settings.episodes):
            obs, _ = env.reset(seed=DATA_SEED + round_ * settings.episodes + k)
            oracle.reset()
            done = False
            while not done:
                action = oracle.act(env.sim, 0)  # the oracle's action from this state
                observations.append(obs)
                actions.append(action if settings.label == "best" else oracle.elite_mean)
                drive = action if policy is None else policy(obs)  # round 0: the oracle drives
                obs, _, terminated, truncated, _ = env.step(drive)
                done = terminated or truncated
        net = fit(np.array(observations), np.array(actions), settings, env.config.obs_size)
        result.fit_error.append(fit_error(net, np.array(observations), np.array(actions)))
        policy = Policy(net, "paper")
        agent = Agent(f"dagger round {round_}", lambda _env, o, p=policy: p(o))
        result.scores.append(score(agent, (track,))[track])
        result.samples.append(len(observations))
    env.close()
    result.seconds = round(time.perf_counter() - start, 1)
    return result


def mean(values: list[float]) -> float:
    return math.fsum(values) / len(values)
