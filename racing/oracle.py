"""A ceiling per track: a planning controller that sees the simulator's true state.

``Oracle`` drives a car by model-predictive control with the simulator itself as the model
(no learning, no observation noise, the exact physics): before every step it copies the car's
state into a batch of ``candidates`` planning cars on the same track, improves a sequence of
``horizon`` actions by the cross-entropy method (``iterations`` rounds: sample action
sequences around the current plan, roll them all out in one batched ``RacingSim``, refit the
plan to the best ``elite`` fraction by total reward), takes the plan's first action and keeps
the rest (shifted) as the next step's starting plan. Rollouts stop adding reward where the
episode would end (the time limit or the finish line), so the plan optimises exactly the
episode's total reward over its horizon.

A policy never sees the true state (only rays and speed) and cannot plan, so the oracle's score
bounds what any policy on this task can be expected to reach; how close the bound is to the
true optimum is measured by how the score grows with ``candidates``, ``horizon`` and
``iterations`` (``python -m speed.oracle_convergence``). Everything random comes from
the oracle's own ``numpy`` generator (``seed``), so a score is reproducible.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from racing.config import RacingConfig
from racing.gym_env import RacingEnv
from racing.sim import RacingSim, check_seed


@dataclass(frozen=True)
class OracleSettings:
    # Chosen by speed/oracle_convergence.py on the tuning tracks 1001-1003 (docs/beyond.md):
    # 4x the candidates or a horizon of 15 change the score by < 1%, longer horizons lower it (the
    # search, not the model, is then the limit), and doubling the rounds from 8 adds 0.9%.
    candidates: int = 256  # action sequences rolled out per round
    horizon: int = 20  # steps planned ahead
    iterations: int = 8  # cross-entropy rounds per step
    elite: float = 0.1  # fraction of the candidates the plan is refitted to
    init_std: float = 0.6  # spread of the sampled actions around the plan, per round reset to this
    min_std: float = 0.05

    def __post_init__(self) -> None:
        for name in ("candidates", "horizon", "iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"oracle {name} must be a positive integer, got {value!r}")
        if not 0 < self.elite <= 1:  # at least one candidate is kept whatever the fraction
            raise ValueError(f"oracle elite must be a fraction in (0, 1], got {self.elite!r}")
        if not 0 < self.min_std <= self.init_std:
            raise ValueError(f"oracle needs 0 < min_std <= init_std, got {self.min_std}, {self.init_std}")


class Oracle:
    """Plans for one car of a ``RacingSim`` (``act(sim, car)``), on that car's current track."""

    STATE = ("x", "y", "theta", "speed", "checkpoint", "t")

    def __init__(self, settings: OracleSettings = OracleSettings(), seed: int = 0):
        self.settings = settings  # the task's constants and the track are the driven simulator's, at each act
        self.rng = np.random.default_rng(check_seed(seed))
        self.planner: RacingSim | None = None  # built for the track driven (``_planner_on``)
        self.reset()

    def reset(self) -> None:
        """Forget the plan (call at the start of an episode): full throttle, straight on, until the
        first round says otherwise."""
        self.plan = np.zeros((self.settings.horizon, 2))
        self.plan[:, 0] = 1.0

    def act(self, sim: RacingSim, car: int = 0) -> np.ndarray:
        """The action ``[throttle, steering]`` for ``sim``'s car ``car`` now."""
        s = self.settings
        steps_left = sim.config.max_steps - int(sim.t[car])
        horizon = max(1, min(s.horizon, steps_left))
        mean, std = self.plan[:horizon].copy(), np.full((horizon, 2), s.init_std)
        n_elite = max(1, round(s.elite * s.candidates))
        best_plan, best_return = mean.copy(), -np.inf
        for _ in range(s.iterations):
            samples = np.clip(mean + std * self.rng.standard_normal((s.candidates, horizon, 2)), -1.0, 1.0)
            samples[0] = mean  # the current plan itself is always a candidate
            returns = self._rollout(sim, car, samples)
            order = np.argsort(-returns, kind="stable")
            if returns[order[0]] > best_return:
                best_return, best_plan = returns[order[0]], samples[order[0]].copy()
            elite = samples[order[:n_elite]]
            mean, std = elite.mean(0), np.maximum(elite.std(0), s.min_std)
        # the rest of the plan, its last action repeated to the full horizon
        self.plan = np.concatenate([best_plan[1:], np.tile(best_plan[-1:], (s.horizon - horizon + 1, 1))])
        self.elite_mean = mean[0].copy()  # the last round's elite mean first action: a smoother label
        return best_plan[0].copy()

    def _planner_on(self, sim: RacingSim, car: int) -> RacingSim:
        """The planning cars, on the track of ``sim``'s car ``car`` and only that one (their memory
        is that track's tables, whatever its size), built again when the car's track changes."""
        track = sim.tracks[car]
        if self.planner is None or self.planner.file_track is not track:
            self.planner = RacingSim(self.settings.candidates, None, sim.config, nearest_ray=sim.nearest_ray,
                                     track=track)
            self.planner.seed(0)
            self.planner.reset()  # start states only (a given track): the rollouts set the state
        return self.planner

    def _rollout(self, sim: RacingSim, car: int, samples: np.ndarray) -> np.ndarray:
        """Total reward of each candidate action sequence from ``sim``'s car ``car``'s state."""
        planner = self._planner_on(sim, car)
        for name in self.STATE:
            getattr(planner, name)[:] = getattr(sim, name)[car]
        planner.finished[:] = False
        if planner.file_track.closed:  # laps count toward config.laps; the planning cars' own lap times are dropped
            planner.laps[:], planner.lap_start[:] = sim.laps[car], sim.lap_start[car]
            for times in planner.lap_times:
                times.clear()
        total = np.zeros(len(samples))
        alive = np.ones(len(samples), dtype=bool)
        for step in range(samples.shape[1]):
            reward, terminated, truncated, _ = planner.step(samples[:, step, 0], samples[:, step, 1])
            total += np.where(alive, reward, 0.0)
            alive &= ~(np.asarray(terminated) | np.asarray(truncated))
            if not alive.any():
                break
        return total


def drive(env, oracle: Oracle, seed: int) -> float:
    """One episode of ``env`` (a ``racing.RacingEnv``) driven by ``oracle`` from the start state of
    ``seed``: its total reward (the same protocol as ``engine.evaluation.run_episode``)."""
    env.reset(seed=seed)
    oracle.reset()
    sim = env.unwrapped.sim
    total, done = 0.0, False
    while not done:
        _, reward, terminated, truncated, _ = env.step(oracle.act(sim, 0))
        total += reward
        done = terminated or truncated
    return total


def score(track_seeds: list[int], episodes: int, seed: int = 0, settings: OracleSettings = OracleSettings(),
          config: RacingConfig = RacingConfig()) -> dict[int, dict]:
    """The oracle's mean total reward on each track over ``episodes`` episodes from the start
    states of ``seed``, ``seed + 1``, ... (``evaluate.py``'s protocol for trained policies), with
    the seconds it took per episode: {track: {"mean": ..., "episodes": [...], "seconds_per_episode": ...}}."""
    results = {}
    for track in track_seeds:
        env = RacingEnv(track_seed=track, **dataclasses.asdict(config))
        oracle = Oracle(settings, seed=seed)
        start = time.perf_counter()
        totals = [drive(env, oracle, seed + episode) for episode in range(episodes)]
        results[track] = {"mean": float(np.mean(totals)), "episodes": totals,
                          "seconds_per_episode": (time.perf_counter() - start) / episodes}
    return results
