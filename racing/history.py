"""A car's history of its own episode: the observations it acted on and the actions it took, newest first.

One rule, kept by ``History`` for every place that needs it: the TorchRL env's ``history`` entry (what
Q-networks may read, ``algo.td.critic_history``) and its observation with past steps (``env.past_steps``:
what every network reads), and a trained policy acting in a Gymnasium env (``engine.evaluation.Policy``), which
keeps its own. At an episode's start the first observation stands for the ones before it and the
actions before it are 0; a respawn after leaving the track is not an episode's start.

The observation with ``k`` past steps is the observation now, then the last ``k`` observations, then
the ``k`` actions taken from them: ``obs_size + k * (obs_size + 2)`` floats.
"""

from __future__ import annotations

import numpy as np

MAX_HISTORY = 64  # past steps a car's history keeps (env.past_steps, algo.td.critic_history)
ACTION_SIZE = 2


def past_size(obs_size: int, steps: int) -> int:
    """The width of an observation with ``steps`` past steps (``steps`` 0: the observation alone)."""
    return obs_size + steps * (obs_size + ACTION_SIZE)


def past_bounds(obs_size: int, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of an observation with past steps: observations in [0, 1], actions in [-1, 1]."""
    low = np.concatenate([np.zeros(obs_size * (1 + steps)), -np.ones(ACTION_SIZE * steps)]).astype(np.float32)
    return low, np.ones_like(low)


def check_steps(name: str, steps) -> int:
    """``steps`` as a number of past steps in [0, MAX_HISTORY]; ``ValueError`` naming ``name`` otherwise."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or not 0 <= steps <= MAX_HISTORY:
        raise ValueError(f"{name} must be an integer in [0, {MAX_HISTORY}] (past steps), got {steps!r}")
    return int(steps)


class History:
    """Each of ``cars`` cars' last ``steps`` observations and actions, newest first.

    ``observe(observation, started)`` after every reset and step (``started``: the rows whose episode
    begins with this observation); ``act(action)`` when the cars act on it. ``flat(k)`` is the last ``k``
    observations then the last ``k`` actions per car, ``(cars, k * (obs + 2))`` float32."""

    def __init__(self, cars: int, steps: int, obs_size: int):
        self.steps = check_steps("steps", steps)
        self.obs = np.zeros((cars, self.steps, obs_size), np.float32)
        self.actions = np.zeros((cars, self.steps, ACTION_SIZE), np.float32)
        self.now: np.ndarray | None = None  # the observation each car acts on next (None before the first)

    def observe(self, observation: np.ndarray, started=None) -> None:
        observation = np.asarray(observation, np.float32)
        if started is not None:
            self.obs[started] = observation[started, None]
            self.actions[started] = 0.0
        self.now = observation.copy()

    def act(self, action: np.ndarray) -> None:
        """The observation acted on and the action taken (clipped to [-1, 1], as the car takes it) join."""
        if self.now is None:
            raise RuntimeError("a car acted before its first observation (reset first)")
        self.obs[:, 1:], self.actions[:, 1:] = self.obs[:, :-1], self.actions[:, :-1]
        self.obs[:, 0], self.actions[:, 0] = self.now, np.clip(action, -1.0, 1.0)

    def flat(self, k: int | None = None) -> np.ndarray:
        k = self.steps if k is None else k
        cars = self.obs.shape[0]
        return np.concatenate([self.obs[:, :k].reshape(cars, -1), self.actions[:, :k].reshape(cars, -1)], axis=1)

    def with_past(self, k: int) -> np.ndarray:
        """The observation now followed by ``flat(k)``: what a policy that reads ``k`` past steps reads."""
        return np.concatenate([self.now, self.flat(k)], axis=1)

    def state_dict(self) -> dict:
        now = self.now if self.now is not None else np.zeros((self.obs.shape[0], self.obs.shape[2]), np.float32)
        return {"history_obs": self.obs.copy(), "history_act": self.actions.copy(), "history_now": now.copy()}

    def check_state(self, state: dict) -> None:
        """``ValueError`` unless ``state`` is a ``state_dict()`` of a history of this one's shape."""
        shapes = {"history_obs": self.obs.shape, "history_act": self.actions.shape,
                  "history_now": (self.obs.shape[0], self.obs.shape[2])}
        for key, shape in shapes.items():
            if state.get(key) is None:
                raise ValueError("the saved state has no history of the cars' observations and actions "
                                 f"(this environment keeps {self.steps} steps)")
            if tuple(np.shape(state[key])) != shape:
                raise ValueError(f"the saved state's {key} has shape {tuple(np.shape(state[key]))}, this environment's "
                                 f"{shape} ({self.obs.shape[0]} cars, {self.steps} past steps): it was saved by "
                                 "another environment")

    def load_state_dict(self, state: dict) -> None:
        """Restore ``state_dict()`` (checked first: nothing changes if it does not fit)."""
        self.check_state(state)
        self.obs[...], self.actions[...] = state["history_obs"], state["history_act"]
        self.now = np.array(state["history_now"], dtype=np.float32)
