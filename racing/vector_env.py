"""The racing task as a native Gymnasium ``VectorEnv``: N cars in one batched ``RacingSim``.

``gym.make_vec("racing/Racing-v0", num_envs=N)`` returns it (the registered vector entry
point; ``vectorization_mode="sync"`` still gives Gymnasium's ``SyncVectorEnv`` of N single
envs). It steps every car with one call of the batched simulator instead of N Python calls,
and computes what N ``RacingEnv`` s compute: a ``SyncVectorEnv`` of them and this env give
identical observations, rewards and flags, step for step, in every autoreset mode
(``tests/test_vector_env.py``).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from racing.gym_env import validate_action
from racing.sim import RacingSim, check_seed
from racing.track_file import env_track

STATE_KEYS = ("x", "y", "theta", "speed", "checkpoint", "step", "progress")


class RacingVectorEnv(VectorEnv):
    """``num_envs`` cars, each with its own track and random stream, stepped together.

    * ``track_seed``: an int (every car on that track), None (a fresh random track for every
      episode of every car) or one of either per car.
    * ``autoreset_mode``: Gymnasium's ``AutoresetMode`` (or its value): ``NEXT_STEP`` (the
      default: the step after an episode's last returns the next episode's first observation,
      reward 0 and no flags), ``SAME_STEP`` (the last step returns the next episode's first
      observation; ``info["final_obs"]`` and ``info["final_info"]`` hold the last episode's)
      or ``DISABLED`` (``reset(options={"reset_mask": mask})`` resets the cars in ``mask``).
    * ``nearest_ray``, ``track_file`` (every car on that file's track; ``track_scale``,
      ``track_closed``) and any field of ``racing.RacingConfig``, as for ``RacingEnv``.

    ``reset(seed=k)`` seeds car i's stream with ``k + i`` (as ``SyncVectorEnv`` seeds its envs);
    a list seeds each car. Actions: an array of shape ``(num_envs, 2)``, [throttle, steering]
    per car (values outside [-1, 1] are clipped; NaN, inf or another shape are refused).
    ``info`` holds each car's ``x, y, theta, speed, checkpoint, step, progress, crashes, crashed,
    finished`` (and on a circuit ``laps``, ``lap_times``) as arrays (with Gymnasium's ``_key``
    masks, all true).
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int, track_seed: int | None | Sequence[int | None] = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, nearest_ray: bool = False,
                 render_mode: str | None = None, track_file: str | None = None, track_scale: float | None = None,
                 track_closed: bool | None = None, **config: Any):
        if render_mode is not None:
            raise ValueError(f"the vector env does not render (render_mode={render_mode!r}); render one car with "
                             "gym.make('racing/Racing-v0', render_mode='rgb_array')")
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        try:
            autoreset_mode = AutoresetMode(autoreset_mode)
        except ValueError:
            raise ValueError(f"autoreset_mode must be one of {[m.value for m in AutoresetMode]}, "
                             f"got {autoreset_mode!r}") from None
        self.num_envs = int(num_envs)
        owner = "RacingVectorEnv (besides num_envs, track_seed, autoreset_mode, nearest_ray, track_file, ...)"
        seeded = track_seed is not None and any(s is not None for s in np.atleast_1d(np.asarray(track_seed, object)))
        track, self.config = env_track(owner, seeded, track_file, track_scale, track_closed, config)
        self.sim = RacingSim(self.num_envs, track_seed, self.config, nearest_ray=nearest_ray, track=track)
        self.metadata = {**self.metadata, "autoreset_mode": autoreset_mode}
        self.autoreset_mode = autoreset_mode
        self.render_mode = None
        self.single_action_space = spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)
        self.single_observation_space = spaces.Box(0.0, 1.0, shape=(self.config.obs_size,), dtype=np.float32)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)  # NEXT_STEP: these cars reset at the next step
        self._crashed = np.zeros(self.num_envs, dtype=bool)
        self._started = False

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict[str, Any] | None = None):
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        if options:
            raise ValueError(f"unknown reset options {sorted(options)}; the only option is 'reset_mask'")
        if mask is not None:
            mask = np.asarray(mask)
            if mask.dtype != np.bool_ or mask.shape != (self.num_envs,):
                raise ValueError(f"reset_mask must be a bool array of shape ({self.num_envs},), got {mask!r}")
        cars = np.arange(self.num_envs) if mask is None else np.flatnonzero(mask)
        if seed is not None:
            if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
                seed = [(check_seed(seed) + i) % 2**32 for i in range(self.num_envs)]
            elif len(seed) != self.num_envs:
                raise ValueError(f"got {len(seed)} seeds for {self.num_envs} cars")
            self.sim.seed([seed[c] for c in cars], cars=cars)
        self.sim.reset(cars)
        self._crashed[cars] = False
        self._autoreset[cars] = False
        self._started = True
        return self._observation(), self._info()

    def step(self, actions):
        if not self._started:
            raise RuntimeError("RacingVectorEnv.step() called before reset()")
        actions = validate_action(actions, (self.num_envs,))
        reward, terminated, truncated, crashed = self.sim.step(actions[:, 0], actions[:, 1])
        reward = np.asarray(reward, dtype=np.float64)
        terminated, truncated = np.asarray(terminated, dtype=bool).copy(), np.asarray(truncated, dtype=bool).copy()
        self._crashed = np.asarray(crashed, dtype=bool).copy()
        if self.autoreset_mode == AutoresetMode.NEXT_STEP:
            restart = np.flatnonzero(self._autoreset)  # their episodes ended last step: this step starts anew
            if restart.size:
                self.sim.reset(restart)
                reward[restart] = 0.0
                terminated[restart] = truncated[restart] = self._crashed[restart] = False
            self._autoreset = terminated | truncated
            return self._observation(), reward, terminated, truncated, self._info()
        observation, info = self._observation(), self._info()
        if self.autoreset_mode == AutoresetMode.SAME_STEP:
            mask = terminated | truncated
            done = np.flatnonzero(mask)
            if done.size:
                final_obs = np.full(self.num_envs, None, dtype=object)
                for car in done:
                    final_obs[car] = observation[car]
                final_info = {key: (mask.copy() if key.startswith("_") else value) for key, value in info.items()}
                self.sim.reset(done)
                self._crashed[done] = False
                observation, info = self._observation(), self._info()
                info.update({"final_obs": final_obs, "_final_obs": mask, "final_info": final_info,
                             "_final_info": mask.copy()})
        return observation, reward, terminated, truncated, info

    def _observation(self) -> np.ndarray:
        return self.sim.observe().astype(np.float32)

    def _info(self) -> dict[str, np.ndarray]:
        sim, n = self.sim, self.config.num_segments
        values = {"x": sim.x.copy(), "y": sim.y.copy(), "theta": sim.theta.copy(), "speed": sim.speed.copy(),
                  "checkpoint": sim.checkpoint.copy(), "step": sim.t.copy(),
                  "progress": (sim.checkpoint + sim.finished) / n, "crashes": sim.crashes.copy(),
                  "crashed": self._crashed.copy(), "finished": sim.finished.copy()}
        if sim.file_track is not None and sim.file_track.closed:
            lap_times = np.empty(self.num_envs, dtype=object)
            lap_times[:] = [list(times) for times in sim.lap_times]
            values.update(laps=sim.laps.copy(), lap_times=lap_times)
        info: dict[str, np.ndarray] = {}
        for key, value in values.items():
            info[key] = value
            info[f"_{key}"] = np.ones(self.num_envs, dtype=bool)
        return info
