"""The racing task as a Gymnasium environment (one car), over ``racing.sim.RacingSim``."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from racing.track_file import env_track
from racing.sim import RacingSim, check_seed

ACTION_HELP = "an action is [throttle, steering], two finite real numbers in [-1, 1]"


def validate_action(action: Any, batch_shape: tuple[int, ...] = ()) -> np.ndarray:
    """Return ``action`` as float64 of shape ``batch_shape + (2,)``, or raise a clear error."""
    try:
        array = np.asarray(action)
    except Exception as exc:  # e.g. ragged nested sequences
        raise TypeError(f"could not read the action {action!r} as an array: {ACTION_HELP}") from exc
    if array.dtype.kind not in "fiu":
        raise TypeError(f"action dtype {array.dtype} is not a real number type: {ACTION_HELP}")
    expected = batch_shape + (2,)
    if array.shape != expected:
        raise ValueError(f"action has shape {array.shape}, expected {expected}: {ACTION_HELP}")
    array = array.astype(np.float64)  # all physics is float64, actions included
    if not np.isfinite(array).all():
        raise ValueError(f"action {array.tolist()} contains NaN or inf: {ACTION_HELP}")
    return array


class RacingEnv(gym.Env):
    """
    ## Description

    A car drives along a randomly generated race track: a chain of 50 quadrilateral
    checkpoints between two walls, each segment turning by up to +-37.5 degrees. Five
    distance sensors look at the walls ahead; the agent sets throttle and steering. The
    simulator reproduces the reference simulator of Holubar & Wiering, "Continuous-action
    Reinforcement Learning for Playing Racing Games: Comparing SPG to PPO", to floating-
    point precision (``docs/specification.md`` states every rule; ``tests/test_conformance.py``).

    ## Action Space

    ``Box(-1, 1, (2,), float32)``; any real dtype is accepted and computed in float64.

    | Num | Action   | Min | Max | Effect                                                         |
    |-----|----------|-----|-----|----------------------------------------------------------------|
    | 0   | throttle | -1  | 1   | target speed (throttle / 2 + 0.5) * max_speed; 5% of the gap closed per step |
    | 1   | steering | -1  | 1   | positive turns left (counter-clockwise); the faster, the wider the turn |

    Values outside [-1, 1] are clipped. NaN, inf, a shape other than (2,) or a non-numeric
    dtype raise ``ValueError`` / ``TypeError``.

    ## Observation Space

    ``Box(0, 1, (6,), float32)``:

    | Num | Observation                                      | Min | Max |
    |-----|--------------------------------------------------|-----|-----|
    | 0   | ray at -45 degrees (right): wall distance / 500  | 0   | 1   |
    | 1   | ray at -22.5 degrees                             | 0   | 1   |
    | 2   | ray straight ahead                               | 0   | 1   |
    | 3   | ray at +22.5 degrees                             | 0   | 1   |
    | 4   | ray at +45 degrees (left)                        | 0   | 1   |
    | 5   | speed / max_speed                                | 0   | 1   |

    A ray sees the walls of the current checkpoint and those ahead of it, up to 500 px;
    1 means nothing within range.

    ## Rewards

    ``speed / max_speed`` every step (so at most 1), minus 10 on a step that leaves the track.

    ## Starting State

    Near the origin, ``x, y ~ U(-0.5, 0.5)``, heading ``U(-5, 5)`` degrees from +y,
    speed 0, checkpoint 0.

    ## Episode End

    * Truncation: after ``max_steps`` (200) steps.
    * Termination: the car leaves the last checkpoint through the finish line
      (``info["finished"]``). Leaving the track anywhere else is not an episode end: the car
      loses one checkpoint and restarts, at rest, from the centre of the checkpoint it is
      put back in, facing along the track. A closed track (a circuit from a file) has no
      finish: the car goes round, each entry into checkpoint 0 from the last completing a lap,
      until ``max_steps``, or until ``laps`` laps (``RacingConfig.laps`` > 0: termination).

    ## Arguments

    ```python
    import gymnasium as gym
    import racing  # registers the environment

    env = gym.make("racing/Racing-v0", track_seed=2067791)
    ```

    * ``track_seed``: an int drives every episode on the track of that seed (the paper's
      tracks are ``racing.PAPER_TRACK_SEEDS``); ``None`` (default) lays out a fresh random
      track at every reset.
    * ``render_mode``: ``"rgb_array"`` or ``"human"`` (both need ``pygame``: ``pip install -c
      constraints/cpu.txt -e '.[render]'``).
    * ``nearest_ray``: read the nearest wall crossing instead of the reference's first in
      scan order (they differ only where a track crosses itself within sensor range).
    * ``track_file``: a track from a CSV file (``racing.track_file``: the TUM racetrack-database's
      columns; ``racing.track_file.example("oval")`` names a shipped one) instead of seeds;
      ``track_scale`` (pixels per file unit) and ``track_closed`` override the file's own
      settings. The file decides ``num_segments``.
    * any field of ``racing.RacingConfig`` (e.g. ``num_segments=10``, ``max_steps=500``).

    ``reset(seed=k)`` re-seeds the car's ``numpy.random.RandomState(k)`` stream; a seeded
    stream lays out a track first (``num_segments`` draws), as the reference simulator did,
    then draws the start state, so ``reset(seed=S)`` on the track of seed ``S`` is the
    reference's first episode exactly. Without a seed the stream continues (unseeded, it
    starts from the fixed track's seed, or from entropy). ``reset(options={"track_seed": k})``
    drives one episode on the track of seed ``k``.

    ``info`` holds the car state (``x``, ``y``, ``theta``, ``speed``, ``checkpoint``), the
    ``step``, the ``track_seed`` (``None`` for an unnamed random track), ``progress``
    (checkpoints passed / ``num_segments``, 1.0 when finished; on a circuit, of the current
    lap), ``crashes`` (steps that left the track so far this episode), ``crashed`` (this step
    left the track) and ``finished``; on a circuit also ``laps`` (completed),
    ``lap_times`` (each lap's steps) and ``lap_seconds`` (at 30 steps a second).

    ## Version History

    * v0: initial version, conformant with the paper's reference simulator.
    """

    metadata = {"render_modes": ["human", "rgb_array"], "render_fps": 30}

    def __init__(self, track_seed: int | None = None, render_mode: str | None = None,
                 nearest_ray: bool = False, track_file: str | None = None, track_scale: float | None = None,
                 track_closed: bool | None = None, **config: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, "
                             f"got {render_mode!r}")
        if track_seed is not None:
            track_seed = check_seed(track_seed, "track_seed")
        owner = "RacingEnv (besides track_seed, render_mode, nearest_ray, track_file, track_scale, track_closed)"
        track, self.config = env_track(owner, track_seed is not None, track_file, track_scale, track_closed, config)
        self.track_seed = track_seed
        self.render_mode = render_mode
        self.sim = RacingSim(1, track_seed, self.config, nearest_ray=nearest_ray, track=track)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.observation_space = spaces.Box(0.0, 1.0, shape=(self.config.obs_size,), dtype=np.float32)
        self._renderer = None
        self.render_lines: list[str] = []  # more text drawn on every frame (films: the agent and its reward so far)
        self._crashed = False

    @property
    def track(self):
        """The track of the current episode (a ``racing.Track``: walls as ``left_wall``,
        ``right_wall`` of shape (N + 1, 2)). With a fixed ``track_seed`` it is known from
        construction on; with ``track_seed=None`` it is ``None`` until the first ``reset()``
        lays one out, and a new one after every reset (also after a reset with the
        ``track_seed`` option, which drives that episode on the seed's track)."""
        return self.sim.tracks[0]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        options = dict(options or {})
        track_seed = options.pop("track_seed", None)
        if options:
            raise ValueError(f"unknown reset options {sorted(options)}; the only option is 'track_seed'")
        if seed is not None:
            self.sim.seed([check_seed(seed)])
        self.sim.reset(track_seed=track_seed)
        self._crashed = False
        if self.render_mode == "human":
            self.render()
        return self._observation(), self._info()

    def step(self, action):
        throttle, steer = validate_action(action).tolist()
        reward, terminated, truncated, self._crashed = self.sim.step_car(throttle, steer)
        if self.render_mode == "human":
            self.render()
        return self._observation(), reward, terminated, truncated, self._info()

    def _observation(self) -> np.ndarray:
        return np.array(self.sim.observe_car(), dtype=np.float32)

    def _info(self) -> dict[str, Any]:
        info = self.sim.car_state(0)
        info["crashed"] = self._crashed
        info["finished"] = bool(self.sim.finished[0])
        return info

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'")
            return None
        if self._renderer is None:
            from racing.render import Renderer

            self._renderer = Renderer(self.config, human=self.render_mode == "human",
                                      fps=self.metadata["render_fps"])
        return self._renderer.draw(self.sim, car=0, extra=self.render_lines)

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
