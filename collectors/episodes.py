"""Collectors that yield one batch of ``[N, steps]`` transitions at a time.

Two interchangeable backends produce the same batches for the same seeds:

- ``"torchrl"``: ``torchrl.collectors.Collector`` over any ``EnvBase`` and a TensorDict policy.
- ``"direct"``: a plain loop over an environment's ``reset_tensors``/``step_tensors`` and a
  tensor-in, tensor-out sampler. It makes the same environment and random-number calls without
  the per-step TensorDict machinery, which dominates the cost of a single car (about 5x faster
  at N = 1; see ``benchmarks/train_speed.py``).

Both reset a car as soon as its episode ends (``done``), so a batch of ``steps`` frames is
exactly one episode per car when episodes last ``steps`` frames, and between batches the
environment is in the same state with either backend.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Protocol

import torch
from tensordict import TensorDict, TensorDictBase

BACKENDS = ("direct", "torchrl")
DONE_KEYS = ("done", "terminated", "truncated")


class TensorStepEnv(Protocol):
    """What the direct backend needs from an environment (``RacingTorchEnv`` provides it)."""

    batch_size: torch.Size

    def reset_tensors(self, cars: torch.Tensor | None = None) -> dict[str, torch.Tensor]: ...

    def step_tensors(self, action: torch.Tensor) -> dict[str, torch.Tensor]: ...


class DirectCollector:
    """Step ``env`` with ``sample(observation) -> action`` and yield ``[N, steps]`` batches.

    The batches have the keys of a TorchRL collector's that the training loop reads:
    ``observation``, ``action``, ``done``/``terminated``/``truncated`` and ``next`` with the
    step's results (``observation``, ``reward``, the done flags and any extra entries).
    """

    def __init__(self, env: TensorStepEnv, sample: Callable[[torch.Tensor], torch.Tensor],
                 steps: int, total_frames: int):
        self.env, self.sample, self.steps = env, sample, steps
        self.carried = tuple(getattr(env, "carried_keys", ("observation",)))  # + the env's privileged state
        self.total_frames = total_frames
        self._state: dict[str, torch.Tensor] | None = None

    def __iter__(self) -> Iterator[TensorDictBase]:
        n = self.env.batch_size[0]
        for _ in range(self.total_frames // (self.steps * n)):
            yield self.collect()

    def collect(self) -> TensorDictBase:
        state = self._state if self._state is not None else self.env.reset_tensors()
        rows: list[dict[str, torch.Tensor]] = []
        for _ in range(self.steps):
            action = self.sample(state["observation"])
            result = self.env.step_tensors(action)
            rows.append({**{key: state[key] for key in self.carried}, "action": action,
                         **{key: state[key] for key in DONE_KEYS}, "next": result})
            state = self._reset_finished(result)
        self._state = state
        return _stack(rows, self.env.batch_size)

    def _reset_finished(self, result: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The state to act on next: cars whose episode just ended are reset at once.

        As TorchRL's ``step_and_maybe_reset`` does, so that between batches both backends
        leave the environment in the same state (checkpoints are taken there).
        """
        done = result["done"]
        if not done.any():
            return {**{key: result[key] for key in self.carried}, **{key: result[key] for key in DONE_KEYS}}
        fresh = self.env.reset_tensors(done)
        keep = ~done
        return {**{key: torch.where(keep, result[key], fresh[key]) for key in self.carried},
                **{key: result[key] & keep for key in DONE_KEYS}}

    def shutdown(self) -> None:
        """Nothing to release (same interface as TorchRL's collectors)."""


def _stack(rows: list[dict[str, torch.Tensor]], batch_size: torch.Size) -> TensorDictBase:
    """Time-major rows -> one TensorDict ``[N, steps]`` (time on dim 1, as TorchRL's)."""
    def stack(key_rows: list) -> dict | torch.Tensor:
        if isinstance(key_rows[0], dict):
            return {key: stack([row[key] for row in key_rows]) for key in key_rows[0]}
        return torch.stack(key_rows, dim=1)

    return TensorDict(stack(rows), batch_size=torch.Size([batch_size[0], len(rows)]))


def make_collector(backend: str, env, *, policy=None, sample=None, steps: int, episodes: int):
    """A collector yielding ``episodes`` batches of ``steps`` frames per car.

    ``backend="torchrl"`` needs ``policy`` (a TensorDict module), ``"direct"`` needs
    ``sample`` (tensor -> tensor) and an env with ``reset_tensors``/``step_tensors``.
    """
    n = env.batch_size[0]
    total = steps * n * episodes
    if backend == "direct":
        if sample is None:
            raise ValueError("the direct collector needs sample=observation -> action")
        return DirectCollector(env, sample, steps, total)
    if backend == "torchrl":
        if policy is None:
            raise ValueError("the torchrl collector needs policy=a TensorDict module")
        from torchrl.collectors import Collector

        # device=env.device: policy, env and storage on one device, so the collector casts nothing
        # (without it, it copies the carried TensorDict .to(env.device) at every step); trust_policy: the
        # policy is the training loop's own module, already there (it may hold no parameter to check)
        return Collector(env, policy, frames_per_batch=steps * n, total_frames=total, device=env.device,
                         trust_policy=True, auto_register_policy_transforms=False)
    raise ValueError(f"collector backend must be one of {BACKENDS}, got {backend!r}")
