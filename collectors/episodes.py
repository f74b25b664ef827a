"""Collectors that yield one batch of ``[N, steps]`` transitions at a time.

Two interchangeable backends produce the same batches for the same seeds:

- ``"torchrl"`` (the default): ``torchrl.collectors.Collector`` over any ``EnvBase`` and a
  TensorDict policy. Its per-step cost is kept near the simulator's by pieces of the design
  itself: the racing env's ``step_and_maybe_reset`` (``RacingTorchEnv``: TorchRL's result without
  its per-step checks), a lean acting policy (``ActingPolicy``) and no trajectory ids (a batch is
  one episode per car).
- ``"direct"``: a plain loop over the environment's ``reset_tensors``/``step_and_reset_tensors``
  and a tensor-in, tensor-out sampler: the same environment and random-number calls with no
  TensorDict per step, the baseline ``speed/train_speed.py`` measures the Collector against.

Both reset a car as soon as its episode ends (``done``), so a batch of ``steps`` frames is
exactly one episode per car when episodes last ``steps`` frames, and between batches the
environment is in the same state with either backend.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Protocol

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase

BACKENDS = ("direct", "torchrl")
DONE_KEYS = ("done", "terminated", "truncated")


class TensorStepEnv(Protocol):
    """What the direct backend needs from an environment (``RacingTorchEnv`` provides it)."""

    batch_size: torch.Size

    def reset_tensors(self, cars: torch.Tensor | None = None) -> dict[str, torch.Tensor]: ...

    def step_and_reset_tensors(self, action: torch.Tensor) -> tuple[dict[str, torch.Tensor],
                                                                    dict[str, torch.Tensor]]: ...


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
            row = {key: state[key] for key in (*self.carried, *DONE_KEYS)}
            # cars whose episode ended are reset at once, as TorchRL's step_and_maybe_reset does, so
            # that between batches both backends leave the env in the same state (checkpoints are taken there)
            result, state = self.env.step_and_reset_tensors(action)
            rows.append({**row, "action": action, "next": result})
        self._state = state
        return _stack(rows, self.env.batch_size)

    def shutdown(self) -> None:
        """Nothing to release (same interface as TorchRL's collectors)."""


class ActingPolicy(TensorDictModuleBase):
    """A tensor sampler (``observation -> action``) as a TensorDict policy for the ``Collector``:
    it reads ``observation`` and writes ``action`` into the TensorDict it is given, with no
    key dispatch per step. Both backends act through the same sampler, so they draw the same
    actions."""

    def __init__(self, sample: Callable[[torch.Tensor], torch.Tensor]):
        super().__init__()
        self.sample = sample
        self.in_keys, self.out_keys = ["observation"], ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # TensorDict's unchecked accessors (tensordict 0.14.3, pinned): the sampler's action has the
        # observation's batch size and device by construction
        action = self.sample(tensordict._get_str("observation", None))
        return tensordict._set_str("action", action, inplace=False, validated=True)


def _stack(rows: list[dict[str, torch.Tensor]], batch_size: torch.Size) -> TensorDictBase:
    """Time-major rows -> one TensorDict ``[N, steps]`` (time on dim 1, as TorchRL's)."""
    def stack(key_rows: list) -> dict | torch.Tensor:
        if isinstance(key_rows[0], dict):
            return {key: stack([row[key] for row in key_rows]) for key in key_rows[0]}
        return torch.stack(key_rows, dim=1)

    return TensorDict(stack(rows), batch_size=torch.Size([batch_size[0], len(rows)]))


def make_collector(backend: str, env, *, policy=None, sample=None, steps: int, episodes: int):
    """A collector yielding ``episodes`` batches of ``steps`` frames per car.

    ``backend="torchrl"`` needs ``policy`` (a TensorDict module; ``ActingPolicy(sample)`` when
    only ``sample`` is given), ``"direct"`` needs ``sample`` (tensor -> tensor) and an env with
    ``reset_tensors``/``step_and_reset_tensors``.
    """
    n = env.batch_size[0]
    total = steps * n * episodes
    if backend == "direct":
        if sample is None:
            raise ValueError("the direct collector needs sample=observation -> action")
        return DirectCollector(env, sample, steps, total)
    if backend == "torchrl":
        if policy is None and sample is None:
            raise ValueError("the torchrl collector needs policy=a TensorDict module or sample=observation -> action")
        from torchrl.collectors import Collector

        # device=env.device: policy, env and storage on one device, so the collector casts nothing
        # (without it, it copies the carried TensorDict .to(env.device) at every step); trust_policy: the
        # policy is the training loop's own module, already there (it may hold no parameter to check);
        # track_traj_ids=False: a batch is one episode per car, and the ids cost a third of a step at N = 1
        return Collector(env, policy if policy is not None else ActingPolicy(sample), frames_per_batch=steps * n,
                         total_frames=total, device=env.device, trust_policy=True, track_traj_ids=False,
                         auto_register_policy_transforms=False)
    raise ValueError(f"collector backend must be one of {BACKENDS}, got {backend!r}")
