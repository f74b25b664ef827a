"""The reactive ceiling: how well an actor network that sees only the observation (five rays and
the speed) drives when it learns from the oracle itself, by DAgger (Ross et al., 2011).

Per track: round 0 lets the oracle drive ``episodes`` episodes and records (observation, the
oracle's action); every later round lets the current network drive (deterministically) and has
the oracle label every state it visits, planning from that state (``racing.oracle.Oracle.act``);
the data of all rounds is aggregated and the network refit from scratch by regression (mean
squared error on the action) after each round. Data episodes start from seeds 1000 + k, the
scoring protocol's episodes from seeds 0-4 (``benchmark.protocol``'s: five deterministic episodes,
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
FEATURES = ("observation", "state")


def pupil_input(env, obs: np.ndarray, features: str) -> np.ndarray:
    """What the pupil sees: the observation, or (``state``, a privileged pupil that is no policy of
    this task) the observation and the car's true state: its position scaled to the track's
    bounding box, the heading's cosine and sine, the checkpoint and the time step as fractions."""
    if features == "observation":
        return obs
    sim = env.unwrapped.sim
    low, high = sim.tracks[0].bounds()
    position = (np.array([sim.x[0], sim.y[0]]) - low) / np.maximum(high - low, 1e-9)
    config = env.unwrapped.config
    return np.concatenate([obs, position, [np.cos(sim.theta[0]), np.sin(sim.theta[0]),
                                           sim.checkpoint[0] / config.num_segments, sim.t[0] / config.max_steps]]
                          ).astype(np.float32)


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
    features: str = "observation"  # the pupil's input: the observation, or "state": it and the car's true state
    noise_states: int = 0  # after the last round: states of it labelled again noise_labels times (label_noise)
    noise_labels: int = 8

    def __post_init__(self) -> None:
        for name in ("episodes", "epochs", "minibatch"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.rounds < 0 or not self.hidden or min(self.hidden) < 1 or not self.lr > 0:
            raise ValueError("rounds must be >= 0, hidden a non-empty list of positive sizes and lr > 0")
        if self.noise_states < 0 or self.noise_labels < 2:
            raise ValueError(f"noise_states must be >= 0 and noise_labels >= 2, got {self.noise_states}, "
                             f"{self.noise_labels}")
        if self.features not in FEATURES:
            raise ValueError(f"features must be one of {FEATURES}, got {self.features!r}")
        if self.label not in LABELS:
            raise ValueError(f"label must be one of {LABELS}, got {self.label!r}")


@dataclass
class DaggerResult:
    track: int
    scores: list[float] = field(default_factory=list)  # the network's protocol score after each round
    samples: list[int] = field(default_factory=list)  # aggregated (observation, action) pairs per round
    fit_error: list[float] = field(default_factory=list)  # the network's mean squared error on its data per round
    label_noise: float | None = None  # the oracle's own spread: mean variance of repeated labels of one state
    error_to_mean_label: float | None = None  # the final network's squared error against those labels' mean
    seconds: float = 0.0


def _tensors(observations: np.ndarray, actions: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """The regression's inputs and targets (actions clipped to [-1, 1])."""
    return (torch.as_tensor(observations, dtype=torch.float32),
            torch.as_tensor(np.clip(actions, -1.0, 1.0), dtype=torch.float32))


def fit(observations: np.ndarray, actions: np.ndarray, settings: DaggerSettings, obs_size: int):
    """A fresh network regressed onto the data (its mean head onto the actions)."""
    from learners.solo import GaussianPolicyNet

    generator = torch.Generator().manual_seed(settings.seed)
    torch.manual_seed(settings.seed)
    net = GaussianPolicyNet(obs_size, 2, list(settings.hidden), "tanh")
    optimiser = torch.optim.Adam(net.parameters(), lr=settings.lr)
    x, y = _tensors(observations, actions)
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


def label(oracle, action: np.ndarray, settings: DaggerSettings) -> np.ndarray:
    """The label of the state ``oracle`` just planned from (``action`` its answer), as ``settings.label`` says."""
    return action if settings.label == "best" else oracle.elite_mean


def fit_error(net, observations: np.ndarray, actions: np.ndarray) -> float:
    """The network's mean squared error on (observation, action) pairs (actions clipped as ``fit``
    trains on them): how far the pupil is from its labels where it has data."""
    x, y = _tensors(observations, actions)
    with torch.no_grad():
        loc, _ = net(x)
        return float(((loc - y) ** 2).mean())


def dagger(track: int, settings: DaggerSettings = DaggerSettings(), oracle_settings=None) -> DaggerResult:
    """DAgger on one track (see the module docstring); the scores are the protocol's."""
    from benchmark.protocol import Agent, score
    from engine.evaluation import Policy
    from racing.gym_env import RacingEnv
    from racing.oracle import Oracle, OracleSettings

    start = time.perf_counter()
    env = RacingEnv(track_seed=track)
    oracle = Oracle(oracle_settings or OracleSettings(), seed=settings.seed)
    observations: list[np.ndarray] = []
    actions: list[np.ndarray] = []
    result = DaggerResult(track)
    policy = None
    visited: list[tuple[np.ndarray, dict]] = []  # the last round's (observation, car state)
    for round_ in range(settings.rounds + 1):
        for k in range(settings.episodes):
            obs, _ = env.reset(seed=DATA_SEED + round_ * settings.episodes + k)
            oracle.reset()
            done = False
            while not done:
                if round_ == settings.rounds and settings.noise_states:
                    visited.append((obs, {name: getattr(env.sim, name)[0].copy() for name in Oracle.STATE}))
                seen = pupil_input(env, obs, settings.features)
                action = oracle.act(env.sim, 0)  # the oracle's action from this state
                observations.append(seen)
                actions.append(label(oracle, action, settings))
                drive = action if policy is None else policy(seen)  # round 0: the oracle drives
                obs, _, terminated, truncated, _ = env.step(drive)
                done = terminated or truncated
        data = np.array(observations), np.array(actions)
        net = fit(*data, settings, len(observations[0]))
        result.fit_error.append(fit_error(net, *data))
        policy = Policy(net, stacked=False)
        agent = Agent(f"dagger round {round_}",
                      lambda driven, o, p=policy: p(pupil_input(driven, o, settings.features)))
        result.scores.append(score(agent, (track,))[track])
        result.samples.append(len(observations))
    if settings.noise_states:
        result.label_noise, result.error_to_mean_label = label_noise(
            env, visited, policy, settings, oracle_settings or OracleSettings())
    env.close()
    result.seconds = round(time.perf_counter() - start, 1)
    return result


def label_noise(env, visited: list, policy, settings: DaggerSettings, oracle_settings) -> tuple[float, float]:
    """How much of the pupil's error is the labels' own: ``settings.noise_states`` states of the last
    round (drawn with ``settings.seed``), each labelled ``settings.noise_labels`` times by oracles of
    seeds 1, 2, ... planning from scratch (no earlier plan). Returns the mean (over states and the
    two action dimensions) of the labels' unbiased variance per state, the error floor of any
    function of the state against single labels, and the pupil's mean squared error against each
    state's mean label. Labels as ``settings.label`` says; actions clipped to [-1, 1]."""
    from racing.oracle import Oracle

    rng = np.random.default_rng(settings.seed)
    picks = rng.choice(len(visited), size=min(settings.noise_states, len(visited)), replace=False)
    oracles = [Oracle(oracle_settings, seed=k + 1) for k in range(settings.noise_labels)]
    variances, errors = [], []
    for index in sorted(picks):
        obs, state = visited[index]
        for name, value in state.items():
            getattr(env.sim, name)[0] = value
        labels = []
        for oracle in oracles:
            oracle.reset()
            labels.append(np.clip(label(oracle, oracle.act(env.sim, 0), settings), -1.0, 1.0))
        labels = np.array(labels)
        variances.append(labels.var(axis=0, ddof=1).mean())
        errors.append(((np.asarray(policy(pupil_input(env, obs, settings.features))) - labels.mean(axis=0)) ** 2).mean())
    return float(np.mean(variances)), float(np.mean(errors))


def mean(values: list[float]) -> float:
    return math.fsum(values) / len(values)
