"""The benchmark protocol: any agent scored on fixed tracks that nothing here was tuned on.

Protocol (``docs/benchmark.md``): the ten generated tracks of ``TRACKS`` (drawn once from
``numpy.random.SeedSequence(20261201)``; no configuration, tuning rule, test or result of this
project names them), ``EPISODES`` = 5 episodes on each from the start states of seeds 0-4, the
environment's defaults (200 steps, crash penalty 10), the agent's deterministic actions. An
agent's score per track is its mean total reward; its benchmark score is the mean over the ten
tracks, with a 95% percentile-bootstrap interval over tracks; its normalised score divides each
track's score by the oracle's on that track (``analysis/data/oracle_benchmark.csv``, shipped),
so 0 is a car that stands still and 1 the oracle.

An agent is named by one string (``load_agent``):
- a ``train.py`` run folder (its final deterministic policy, under the numerics it was trained in);
- a Stable-Baselines3 ``model.zip`` (``predict(obs, deterministic=True)``), or a ``baseline.py`` run
  folder (its ``model.zip``);
- ``module:function``: a Python callable ``observation (6 floats) -> [throttle, steering]``
  (the module importable from the working directory);
- ``oracle``, ``pure_pursuit``, ``ray_follower``: the project's reference drivers (the first
  two see the simulator's true state and the track; the ray follower only the observation).
"""

from __future__ import annotations

import importlib
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable


TRACKS = (3011430478, 3667900085, 3988919934, 1407878595, 3364933968, 2100856258, 2610483764, 1931060112,
          3123763360, 383847979)  # [int(s) for s in numpy.random.SeedSequence(20261201).generate_state(10)]
EPISODES = 5
ORACLE_SCORES = Path(__file__).resolve().parent.parent / "analysis" / "data" / "oracle_benchmark.csv"
BUILTIN = ("oracle", "pure_pursuit", "ray_follower")


class AgentError(ValueError):
    """An agent specification that names nothing usable; the message says what was expected."""


@dataclass
class Agent:
    """Something that drives: ``reset()`` at each episode's start, ``act(env, observation)`` each step
    (``env``: the ``racing.RacingEnv``; privileged drivers read ``env.unwrapped.sim``)."""

    name: str
    act: Callable
    reset: Callable = lambda: None
    kind: str = "callable"


def load_agent(spec: str) -> Agent:
    """The agent a specification names (see the module docstring); ``AgentError`` otherwise."""
    if spec in BUILTIN:
        return _builtin(spec)
    path = Path(spec)
    if path.is_dir() and os.path.lexists(path / "model.zip") and not os.path.lexists(path / "actor.pt"):
        from engine import rundir

        found = rundir.state(path)  # a run folder of baseline.py (Stable-Baselines3): by the folder rules
        if found.kind == "damaged":
            raise AgentError(found.refusal().split(". Its files")[0] + "; it is not scored")
        return _sb3(path / "model.zip")
    if path.is_dir():
        from engine.evaluation import RunFolderError, load_policy

        try:
            policy, _ = load_policy(path)
        except RunFolderError as err:
            raise AgentError(str(err)) from None
        return Agent(str(path), lambda env, obs: policy(obs), policy.reset, kind="run folder")
    if path.suffix == ".zip":
        return _sb3(path)
    if ":" in spec and not path.exists():
        return _callable(spec)
    raise AgentError(f"{spec!r} names no agent: give a train.py run folder, a Stable-Baselines3 model.zip, "
                     f"module:function (a callable observation -> action), or one of {', '.join(BUILTIN)}")


def _builtin(name: str) -> Agent:
    if name == "ray_follower":
        from racing.driver import ray_follower

        return Agent(name, lambda env, obs: ray_follower(obs), kind="reference (observation only)")
    if name == "pure_pursuit":
        from racing.driver import PurePursuit

        driver = PurePursuit()
    else:
        from racing.oracle import Oracle

        driver = Oracle()
    return Agent(name, lambda env, obs: driver.act(env.unwrapped.sim, 0), driver.reset, kind="reference (true state)")


def _sb3(path: Path) -> Agent:
    """A Stable-Baselines3 model.zip as weights only (``external.sb3.load_model``: nothing in it runs)."""
    try:
        import stable_baselines3  # noqa: F401
    except ImportError:
        raise AgentError("scoring a model.zip needs Stable-Baselines3: pip install -c constraints/cpu.txt "
                         "-e '.[baselines]'") from None
    from external.sb3 import ModelRefused, load_model

    try:
        policy, algo = load_model(path)
    except ModelRefused as err:
        raise AgentError(str(err)) from None
    return Agent(str(path), lambda env, obs: policy.predict(obs, deterministic=True)[0],
                 kind=f"Stable-Baselines3 {algo}")


def _callable(spec: str) -> Agent:
    module_name, _, attribute = spec.partition(":")
    if "" not in sys.path and "." not in sys.path:
        sys.path.insert(0, "")  # modules of the working directory, as `python -m` finds them
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise AgentError(f"{spec}: cannot import module {module_name!r} ({err})") from None
    function = getattr(module, attribute, None)
    if not callable(function):
        raise AgentError(f"{spec}: module {module_name!r} has no callable {attribute!r}")
    return Agent(spec, lambda env, obs: function(obs))


def run_episode(agent: Agent, env, seed: int, frames: list | None = None) -> float:
    """One episode of ``agent`` from the start state of ``seed``: its total reward
    (``engine.evaluation.drive_episode``). An agent that raises is an ``AgentError`` naming the
    agent and its error."""
    from engine.evaluation import drive_episode

    def act(env, obs):
        try:
            return agent.act(env, obs)
        except Exception as err:  # the agent's own code: any error, said in one line
            raise AgentError(f"the agent raised {type(err).__name__}: {err}") from err

    return drive_episode(act, env, seed, frames, agent.reset, name=agent.name)


def lap_times(agent: Agent, track, laps: int = 3, seed: int = 0, max_steps: int | None = None) -> dict:
    """``agent`` on a circuit (a ``racing.track_file.FileTrack`` or a file's path) from the start
    state of ``seed`` until it has driven ``laps`` laps (``RacingConfig.laps``) or ``max_steps``
    steps (default: ``laps`` times four times the steps the centre line takes at full speed):
    {"laps", "lap_seconds", "best_lap_s", "crashes", "total_reward", "steps"}."""
    from racing.config import MAX_STEPS, RacingConfig
    from racing.gym_env import RacingEnv
    from racing.track_file import FileTrack, env_keywords, load_track

    track = track if isinstance(track, FileTrack) else FileTrack(str(track))
    circuit = load_track(track.path, track.scale, track.closed)
    if not circuit.closed:
        raise ValueError(f"{track.path} is read as an open track, which has no laps (a circuit: --track-closed)")
    full_speed_steps = circuit.centre_line_length() / RacingConfig().max_speed
    cap = max_steps or min(MAX_STEPS, int(laps * 4 * full_speed_steps) + 1_000)
    env = RacingEnv(**env_keywords(track), max_steps=cap, laps=laps)
    total = run_episode(agent, env, seed)
    sim = env.unwrapped.sim
    seconds = [round(steps * sim.STEP_SECONDS, 3) for steps in sim.lap_times[0]]
    env.close()
    return {"laps": int(sim.laps[0]), "lap_seconds": seconds, "best_lap_s": min(seconds) if seconds else None,
            "crashes": int(sim.crashes[0]), "total_reward": total, "steps": int(sim.t[0])}


def film(agent: Agent, track: int | str, path: Path, seed: int = 0, **options) -> tuple[int, float]:
    """One episode of ``agent`` on a track (a seed or a track file) as a GIF or MP4, with the
    agent's name, its reward so far, the progress, a map of the track and, on a circuit, the laps
    drawn; returns (frames, total reward)."""
    from engine.evaluation import check_video_path, write_video
    from racing.gym_env import RacingEnv

    check_video_path(path)
    from racing.track_file import env_keywords

    env = RacingEnv(render_mode="rgb_array", **env_keywords(track), **options)
    frames: list = []
    total = run_episode(agent, env, seed, frames)
    env.close()
    return write_video(frames, path), total


def score(agent: Agent, tracks=TRACKS, episodes: int = EPISODES, first_seed: int = 0) -> dict[int, float]:
    """{track: mean total reward over ``episodes`` episodes from start seeds ``first_seed``, ...}."""
    from racing.gym_env import RacingEnv

    if agent.name == "oracle":  # the planner's own protocol (racing.oracle.score): the shipped scores exactly
        from racing import oracle

        return {track: result["mean"] for track, result in oracle.score(list(tracks), episodes, first_seed).items()}
    results = {}
    for track in tracks:
        env = RacingEnv(track_seed=track)
        results[track] = math.fsum(run_episode(agent, env, first_seed + e) for e in range(episodes)) / episodes
        env.close()
    return results


def read_oracle(path: Path = ORACLE_SCORES) -> dict[int, float]:
    """{track: the oracle's mean total reward} for the benchmark tracks (shipped)."""
    from door import files

    return {int(row["track"]): float(row["mean_reward"]) for row in files.read_csv(path, 1 << 20, "oracle table")}


def summarise(per_track: dict[int, float], oracle: dict[int, float]) -> dict:
    """The benchmark score and the normalised score, each with its 95% interval over tracks."""
    from analysis.compare import bootstrap_interval

    tracks = list(per_track)
    raw = [per_track[t] for t in tracks]
    normalised = [per_track[t] / oracle[t] for t in tracks if t in oracle]
    summary = {"tracks": len(tracks), "mean": math.fsum(raw) / len(raw), "ci": bootstrap_interval(raw)}
    if len(normalised) == len(tracks):
        summary.update(normalised=math.fsum(normalised) / len(normalised), normalised_ci=bootstrap_interval(normalised))
    return summary


def check_score(value: float, track: int) -> str | None:
    """Why ``value`` cannot be an agent's mean total reward on benchmark ``track`` under the protocol
    (None: it can): a track the protocol does not score, or a value that is not finite or lies outside
    what an episode of the environment's defaults can total (each step's reward lies in
    [-crash_penalty, 1])."""
    from racing.config import RacingConfig

    if track not in TRACKS:
        return f"track {track} is not one of the benchmark's tracks"
    config = RacingConfig()
    low, high = -config.crash_penalty * config.max_steps, float(config.max_steps)
    if not math.isfinite(value) or not low <= value <= high:
        return (f"mean total reward {value!r} is not a finite number in [{low:g}, {high:g}] (what an episode of "
                f"{config.max_steps} steps can total)")
    return None
