"""Experience replay: the transition memory and the three schedules of the paper.

``recent`` trains on the newest episode after collecting it; ``memory`` trains on the replay
memory before collecting (the newest episode joins the memory, and so the training, one
episode later); ``hybrid`` does both, with each phase's minibatch scaled by
``minibatch_fraction`` (0.5 in the paper) so that the transitions seen per episode stay the same.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, RandomSampler, TensorDictReplayBuffer


@dataclass(frozen=True)
class ReplaySchedule:
    """When to train and on what: see the module docstring."""

    name: str
    train_on_memory: bool
    train_on_recent: bool
    minibatch_fraction: float

    def minibatch_size(self, base: int) -> int:
        return max(1, round(base * self.minibatch_fraction))


class ReplayMemory:
    """A ring buffer of transitions (oldest overwritten), on a TorchRL ``TensorDictReplayBuffer``."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity), sampler=RandomSampler())

    def __len__(self) -> int:
        return len(self.buffer)

    def add(self, transitions: TensorDictBase) -> None:
        self.buffer.extend(transitions)

    def state_dict(self) -> dict:
        """Storage (in slot order) and write cursor: restoring them continues the ring exactly."""
        return self.buffer.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.buffer.load_state_dict(state)

    def contents(self) -> TensorDictBase:
        """Every stored transition (in slot order, not time order), as a new TensorDict."""
        return self.buffer[:].clone()


def sample_minibatch(data: TensorDictBase, size: int, generator: torch.Generator | None = None) -> TensorDictBase:
    """``size`` transitions drawn uniformly WITH replacement from ``data`` (a flat TensorDict)."""
    index = torch.randint(len(data), (size,), generator=generator)
    # Indexing each entry is cheaper than TensorDict indexing, which this is called for 10^4
    # times per run; nested entries take the general path.
    if any(isinstance(value, TensorDictBase) for value in data.values()):
        return data[index]
    return TensorDict({key: value[index] for key, value in data.items()}, batch_size=[size])
