"""The racing task as a natively batched TorchRL environment, over ``racing.sim.RacingSim``."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from racing.config import RacingConfig
from racing.gym_env import ACTION_HELP
from racing.sim import RacingSim


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
        **config: fields of ``racing.RacingConfig``.

    Keys: ``observation`` (N, 6) float32 in [0, 1]; ``action`` (N, 2) float32 in [-1, 1]
    (clipped); ``reward`` (N, 1) float32; ``done``, ``terminated``, ``truncated`` (N, 1) bool;
    and, for logging, ``checkpoint`` (N, 1) int64 and ``crashed`` (N, 1) bool (this step
    left the track). ``env.set_seed(k)`` seeds car i's stream with ``k + i``.
    """

    def __init__(self, num_envs: int = 1, track_seeds: int | None | Sequence[int | None] = None,
                 device: Any = "cpu", nearest_ray: bool = False, **config: Any):
        cfg = RacingConfig.from_keywords("RacingTorchEnv (besides num_envs, track_seeds, device, nearest_ray)",
                                         **config)
        self.sim = RacingSim(num_envs, track_seeds, cfg, nearest_ray=nearest_ray)
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        self.config = cfg
        n = (num_envs,)
        self.observation_spec = Composite(
            observation=Bounded(0.0, 1.0, n + (cfg.obs_size,), dtype=torch.float32, device=self.device),
            checkpoint=Bounded(0, cfg.num_segments - 1, n + (1,), dtype=torch.int64, device=self.device),
            crashed=Categorical(2, n + (1,), dtype=torch.bool, device=self.device),
            shape=n,
        )
        self.action_spec = Bounded(-1.0, 1.0, n + (2,), dtype=torch.float32, device=self.device)
        self.reward_spec = Unbounded(n + (1,), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            {key: Categorical(2, n + (1,), dtype=torch.bool, device=self.device)
             for key in ("done", "terminated", "truncated")},
            shape=n,
        )

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        cars = None
        if tensordict is not None and "_reset" in tensordict.keys():
            cars = tensordict["_reset"].reshape(-1).cpu().numpy().nonzero()[0]
        self.sim.reset(cars)
        flags = torch.zeros(self.batch_size + (1,), dtype=torch.bool)
        return self._pack(crashed=flags, done=flags, terminated=flags, truncated=flags)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict["action"]
        if action.shape != self.batch_size + (2,):
            raise ValueError(f"action has shape {tuple(action.shape)}, expected "
                             f"{tuple(self.batch_size + (2,))}: {ACTION_HELP}")
        if action.is_complex() or not (action.is_floating_point() or action.dtype in _INTEGER):
            raise TypeError(f"action dtype {action.dtype} is not a real number type: {ACTION_HELP}")
        a = action.detach().to("cpu", torch.float64).numpy()
        if not np.isfinite(a).all():
            bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
            raise ValueError(f"actions of cars {bad[:8].tolist()} contain NaN or inf: {ACTION_HELP}")
        reward, terminated, truncated, crashed = self.sim.step(a[:, 0], a[:, 1])
        terminated, truncated = _column(terminated), _column(truncated)
        return self._pack(
            reward=torch.from_numpy(reward.astype(np.float32)).unsqueeze(-1),
            crashed=_column(crashed), done=terminated | truncated,
            terminated=terminated, truncated=truncated,
        )

    def _pack(self, **entries: torch.Tensor) -> TensorDictBase:
        entries["observation"] = torch.from_numpy(self.sim.observe().astype(np.float32))
        # A copy: the simulator updates its state arrays in place.
        entries["checkpoint"] = torch.from_numpy(self.sim.checkpoint.copy()).unsqueeze(-1)
        td = TensorDict(entries, batch_size=self.batch_size)
        return td if self.device == torch.device("cpu") else td.to(self.device)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self.sim.seed(seed)


_INTEGER = (torch.int8, torch.int16, torch.int32, torch.int64, torch.uint8)


def _column(flags: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(flags)).unsqueeze(-1)
