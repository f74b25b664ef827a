"""The racing task as a natively batched TorchRL environment, over ``racing.sim.RacingSim``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from racing.gym_env import ACTION_HELP
from racing.history import History, check_steps, past_bounds
from racing.sim import RacingSim
from racing.track_file import env_track


class RacingTorchEnv(EnvBase):
    """N cars stepped together (``batch_size=[N]``), each on its own track.

    Same physics, random streams and conventions as ``racing.RacingEnv`` (see its docstring);
    ``RacingTorchEnv(track_seeds=[s])`` seeded with ``k`` and ``RacingEnv(track_seed=s)``
    reset with ``seed=k`` produce identical episodes.

    Args:
        num_envs: number of cars N.
        track_seeds: an int (every car on that track), ``None`` (a fresh random track per
            car at every reset) or one entry per car.
        device: where the returned tensors live (the simulation itself runs on the CPU).
        nearest_ray: see ``racing.RacingEnv``.
        track_file: every car on the track of this file (``racing.track_file``; with
            ``track_scale``, ``track_closed``), as for ``racing.RacingEnv``.
        **config: fields of ``racing.RacingConfig``.

    Keys: ``observation`` (N, 6) float32 in [0, 1]; ``action`` (N, 2) float32 in [-1, 1]
    (clipped); ``reward`` (N, 1) float32; ``done``, ``terminated``, ``truncated`` (N, 1) bool;
    and, for logging, ``checkpoint`` (N, 1) int64 and ``crashed`` (N, 1) bool (this step
    left the track). With ``privileged=True`` also ``privileged`` (N, 4) float32: each car's true state
    in its track's frame (``RacingSim.true_state``), for critics that train on it; no policy sees it.
    With ``history=k`` also ``history`` (N, k * (obs + 2)) float32: the car's k observations before this
    one, newest first, then the k actions it took from them, newest first; at an episode's start the
    first observation stands for the ones before it and the actions are 0 (a respawn after leaving the
    track is not an episode's start; ``racing.history``). With ``past_steps=k`` the ``observation`` itself is
    (N, 6 + k * (6 + 2)): the observation now, then the car's last k observations and k actions as in
    ``history`` (what every network reads: a policy with past steps). ``sim_state`` / ``load_sim_state`` save
    and restore both with the cars.
    ``env.set_seed(k)`` seeds car i's stream with ``k + i``.
    """

    def __init__(self, num_envs: int = 1, track_seeds: int | None | Sequence[int | None] = None,
                 device: Any = "cpu", nearest_ray: bool = False, track_file: str | None = None,
                 track_scale: float | None = None, track_closed: bool | None = None, privileged: bool = False,
                 history: int = 0, past_steps: int = 0, **config: Any):
        owner = "RacingTorchEnv (besides num_envs, track_seeds, device, nearest_ray, track_file, ...)"
        seeded = track_seeds is not None and any(s is not None for s in np.atleast_1d(np.asarray(track_seeds, object)))
        track, cfg = env_track(owner, seeded, track_file, track_scale, track_closed, config)
        self.sim = RacingSim(num_envs, track_seeds, cfg, nearest_ray=nearest_ray, track=track)
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.config = cfg
        self._on_cpu = self.device == torch.device("cpu")
        self._continue = False  # see load_sim_state
        if not isinstance(privileged, (bool, np.bool_)):
            raise TypeError(f"privileged must be True or False, got {privileged!r}")
        self.privileged = bool(privileged)
        self.history = check_steps("history", history)
        self.past_steps = check_steps("past_steps", past_steps)
        # the cars' past observations and actions, as long as the longer of the two needs
        self._past = History(num_envs, max(self.history, self.past_steps), cfg.obs_size)
        # what a collector carries from a step's result to the next step's root (besides the done flags)
        self.carried_keys = ("observation", *(("privileged",) if self.privileged else ()),
                             *(("history",) if self.history else ()))
        n = (num_envs,)
        low, high = past_bounds(cfg.obs_size, self.past_steps)
        self.observation_spec = Composite(
            observation=Bounded(torch.from_numpy(low).expand(n + low.shape),
                                torch.from_numpy(high).expand(n + low.shape), n + low.shape, dtype=torch.float32,
                                device=self.device),
            checkpoint=Bounded(0, cfg.num_segments - 1, n + (1,), dtype=torch.int64, device=self.device),
            crashed=Categorical(2, n + (1,), dtype=torch.bool, device=self.device),
            shape=n,
        )
        if self.privileged:
            self.observation_spec["privileged"] = Unbounded(n + (len(RacingSim.TRUE_STATE),), dtype=torch.float32,
                                                            device=self.device)
        if self.history:
            self.observation_spec["history"] = Unbounded(n + (self.history * (cfg.obs_size + 2),), dtype=torch.float32,
                                                         device=self.device)
        self.action_spec = Bounded(-1.0, 1.0, n + (2,), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded(n + (1,), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            {key: Categorical(2, n + (1,), dtype=torch.bool, device=self.device)
             for key in ("done", "terminated", "truncated")},
            shape=n,
        )

    @property
    def tracks(self) -> list:
        """Each car's current track (``racing.Track``): a fixed track (an int in ``track_seeds``)
        from construction on; a random one (``None``) from the car's first reset, new at each."""
        return list(self.sim.tracks)

    def load_sim_state(self, state: dict) -> None:
        """Restore the simulator from ``env.sim.state_dict()`` (cars, tracks, random streams).

        The next full reset then continues the restored cars where they are (it resets only
        those whose episode had ended) instead of starting new episodes. So a collector built
        after restoring, whose first act is a full reset, carries on exactly where the saved
        run stopped.
        """
        state = dict(state)
        past = {key: state.pop(key, None) for key in ("history_obs", "history_act", "history_now")}
        if self._past.steps:
            self._past.check_state(past)  # before any car is touched
        self.sim.load_state_dict(state)
        if self._past.steps:
            self._past.load_state_dict(past)
        self._continue = True

    def sim_state(self) -> dict:
        """``sim.state_dict()`` and, with ``history`` or ``past_steps``, the cars' past observations and actions:
        what ``load_sim_state`` continues exactly from."""
        state = self.sim.state_dict()
        if self._past.steps:  # before the first reset: no observation yet (zeros, as the history)
            state.update(self._past.state_dict())
        return state

    # A lean path for collectors that step thousands of times per second: the same
    # simulator calls and checks as ``reset``/``step``, without TensorDict bookkeeping.
    def reset_tensors(self, cars: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Reset the cars marked in ``cars`` (bool, shape (N,) or (N, 1); default all).

        Returns the entries of ``reset()`` as a dict of tensors (observation of every car).
        """
        rows = None if cars is None else cars.reshape(-1).cpu().numpy().nonzero()[0]
        if self._continue:  # the first reset after load_sim_state
            self._continue = False
            if rows is None:
                rows = np.flatnonzero(self.sim.finished | (self.sim.t >= self.config.max_steps))
        self.sim.reset(rows)
        return self._entries(_reset=np.arange(self.sim.num_cars) if rows is None else rows,
                             **{key: torch.zeros(self.batch_size + (1,), dtype=torch.bool)
                                for key in ("crashed", "done", "terminated", "truncated")})

    def step_tensors(self, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """Step every car; returns the entries of ``step()["next"]`` as a dict of tensors."""
        a = self._checked_action(action)
        if self._past.steps:  # the observation acted on and the action taken join the history
            self._past.act(a)
        reward, terminated, truncated, crashed = self.sim.step(a[:, 0], a[:, 1])
        # One fresh (N, 4) array, handed out as four column views that share nothing else.
        flags = torch.from_numpy(np.stack([terminated | truncated, terminated, truncated, crashed], axis=1))
        return self._entries(reward=_column(reward.astype(np.float32)), done=flags[:, 0:1],
                             terminated=flags[:, 1:2], truncated=flags[:, 2:3], crashed=flags[:, 3:4])

    def step_and_reset_tensors(self, action: torch.Tensor) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Step every car, then reset the cars whose episode ended, as TorchRL's
        ``step_and_maybe_reset`` does: the step's entries, and the entries to act on next (the
        step's, without the reward, with a fresh start for each finished car)."""
        result = self.step_tensors(action)
        following = {key: value for key, value in result.items() if key != "reward"}
        done = result["done"]
        if done.any():
            fresh, keep = self.reset_tensors(done), ~done
            following = {key: torch.where(keep, value, fresh[key]) for key, value in following.items()}
        return result, following

    def _step_and_maybe_reset(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        """What ``EnvBase.step_and_maybe_reset`` returns (the step's data with ``"next"``, and the
        next step's root: the step's entries, finished cars reset, the root's other keys kept), at
        the cost of the simulator: the entries are the simulator's own, checked once
        (``step_tensors``), so the per-step TensorDict checks, done completion and ``step_mdp``
        are skipped. TorchRL's ``Collector`` calls it at every step. A subclass that changes
        ``_step`` or ``_reset``, or an env with post-step hooks, takes TorchRL's own path."""
        if (type(self)._step is not RacingTorchEnv._step or type(self)._reset is not RacingTorchEnv._reset
                or self._post_step_mdp_hooks is not None or self.__dict__.get("_torchrl_native_autoreset")):
            return super()._step_and_maybe_reset(tensordict)
        if tensordict.device != self.device:
            tensordict = tensordict.to(self.device)
        # TensorDict's own unchecked accessors (tensordict 0.14.3, pinned): the entries are the simulator's,
        # of this env's batch size and device, so TensorDict's per-entry checks would only repeat ours
        result, following = self.step_and_reset_tensors(tensordict._get_str("action", None))
        tensordict._set_str("next", self._pack(result), inplace=False, validated=True)
        root = dict(tensordict._tensordict)  # the root's other keys (the policy's, a collector's) carry over
        del root["next"]
        root.update(following)
        return tensordict, self._pack(root)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        cars = None
        if tensordict is not None and "_reset" in tensordict.keys():
            cars = tensordict["_reset"]
        return self._pack(self.reset_tensors(cars))

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        return self._pack(self.step_tensors(tensordict["action"]))

    def _checked_action(self, action: torch.Tensor) -> np.ndarray:
        if not isinstance(action, torch.Tensor):
            raise TypeError(f"action must be a torch.Tensor, got {type(action).__name__}: {ACTION_HELP}")
        if action.shape != self.batch_size + (2,):
            raise ValueError(f"action has shape {tuple(action.shape)}, expected "
                             f"{tuple(self.batch_size + (2,))}: {ACTION_HELP}")
        if action.is_complex() or not (action.is_floating_point() or action.dtype in _INTEGER):
            raise TypeError(f"action dtype {action.dtype} is not a real number type: {ACTION_HELP}")
        a = action.detach().cpu().numpy().astype(np.float64)
        if not np.isfinite(a).all():
            bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
            raise ValueError(f"actions of cars {bad[:8].tolist()} contain NaN or inf: {ACTION_HELP}")
        return a

    def _entries(self, _reset: np.ndarray | None = None, **entries: torch.Tensor) -> dict[str, torch.Tensor]:
        """The entries of every car after a step, or after a reset of the cars ``_reset``."""
        observation = self.sim.observe().astype(np.float32)
        if self._past.steps:  # a new episode: its first observation stands for the ones before it
            self._past.observe(observation, started=_reset)
        if self.past_steps:
            observation = self._past.with_past(self.past_steps)
        entries["observation"] = torch.from_numpy(observation)
        entries["checkpoint"] = _column(self.sim.checkpoint.copy())  # a copy: updated in place
        if self.privileged:
            entries["privileged"] = torch.from_numpy(self.sim.true_state().astype(np.float32))
        if self.history:
            entries["history"] = torch.from_numpy(self._past.flat(self.history))
        if not self._on_cpu:
            entries = {key: value.to(self.device) for key, value in entries.items()}
        return entries

    def _pack(self, entries: dict[str, torch.Tensor]) -> TensorDictBase:
        """A TensorDict of entries this env made (their shapes and device are its own, so
        TensorDict's per-entry checks are skipped: ``_new_unsafe``, tensordict's own constructor
        for that case)."""
        return TensorDict._new_unsafe(entries, batch_size=self.batch_size, device=self.device)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self.sim.seed(seed)


_INTEGER = (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)


def _column(values: np.ndarray) -> torch.Tensor:
    """(N,) array -> (N, 1) tensor sharing its memory (callers pass arrays nobody else holds)."""
    return torch.from_numpy(np.ascontiguousarray(values).reshape(-1, 1))
