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

from collectors.prioritised import ProportionalSampler


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
    """A ring buffer of transitions (oldest overwritten), on a TorchRL ``TensorDictReplayBuffer``.

    With ``members=R`` it holds one memory per member of a population in one storage: each
    slot is a row of R transitions (one per member; members add the same number at a time),
    ``add`` takes ``[R, T]`` and ``contents`` gives ``[R, n]``. ``capacity`` counts
    transitions per member either way.
    """

    def __init__(self, capacity: int, members: int | None = None, device: torch.device | str = "cpu",
                 priority=None):
        """``priority``: None (uniform sampling) or options with ``alpha``, ``beta``, ``eps`` for
        proportional prioritised sampling (``collectors.prioritised``; then ``sampler`` holds the
        priorities, saved with the memory)."""
        self.capacity = capacity
        self.members = members
        self.device = torch.device(device)
        self.sampler = (ProportionalSampler(capacity, priority.alpha, priority.beta, priority.eps, members=members)
                        if priority is not None else None)
        # compilable: the storage's and writer's counters as plain values, not multiprocessing ones
        # (shared-memory semaphores, whose helper process turns a SLURM signal into tracebacks);
        # the memory lives in one process
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity, device=device, compilable=True),
                                             sampler=self.sampler if self.sampler is not None else RandomSampler(),
                                             compilable=True)

    def __len__(self) -> int:
        """Transitions stored (per member)."""
        return len(self.buffer)

    def add(self, transitions: TensorDictBase) -> None:
        if self.members is not None:
            if transitions.batch_dims != 2 or transitions.batch_size[0] != self.members:
                raise ValueError(f"a population memory of {self.members} members takes [members, T] "
                                 f"transitions, got batch size {tuple(transitions.batch_size)}")
            transitions = transitions.transpose(0, 1)
        self.buffer.extend(transitions)

    def state_dict(self) -> dict:
        """Storage (in slot order) and write cursor: restoring them continues the ring exactly."""
        return self.buffer.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.buffer.load_state_dict(_to_device(state, self.device))

    def contents(self) -> TensorDictBase:
        """Every stored transition (in slot order, not time order), as a new TensorDict
        (``[n]``, or ``[R, n]`` for a population)."""
        data = self.buffer[:]
        return data.clone() if self.members is None else data.transpose(0, 1).contiguous()


def sample_minibatch(data: TensorDictBase, size: int,
                     generators: torch.Generator | list[torch.Generator] | None = None) -> TensorDictBase:
    """``size`` transitions drawn uniformly WITH replacement from ``data``.

    ``data`` is flat (``[n]``; one ``generator`` or None for torch's global one), or a
    population's ``[R, n]`` with one generator per member: member r's minibatch comes from
    its own transitions, with indices from ``generators[r]``; the result is ``[R, size]``.
    """
    if isinstance(generators, (list, tuple)):
        if data.batch_dims != 2 or data.batch_size[0] != len(generators):
            raise ValueError(f"{len(generators)} generators need data of batch size [{len(generators)}, n], "
                             f"got {tuple(data.batch_size)}")
        return TensorDict(member_minibatch(dict(data.items()), data.batch_size[1], size, generators),
                          batch_size=[len(generators), size])
    index = torch.randint(len(data), (size,), generator=generators)
    # Indexing each entry is cheaper than TensorDict indexing, which this is called for 10^4
    # times per run; nested entries take the general path.
    if any(isinstance(value, TensorDictBase) for value in data.values()):
        return data[index]
    return TensorDict({key: value[index] for key, value in data.items()}, batch_size=[size])


def member_minibatch(tensors: dict[str, torch.Tensor], n: int, size: int,
                     generators: list[torch.Generator]) -> dict[str, torch.Tensor]:
    """``sample_minibatch`` of a population on plain tensors ``[R, n, ...]``: ``size`` rows per member,
    drawn uniformly WITH replacement, member r's indices from ``generators[r]``; ``{key: [R, size, ...]}``."""
    index = torch.stack([torch.randint(n, (size,), generator=g, device=g.device) for g in generators])
    rows = torch.arange(len(generators), device=index.device).unsqueeze(1)
    return {key: value[rows, index] for key, value in tensors.items()}


def sample_sub_episodes(data: TensorDictBase, size: int, length: int, episode_steps: int,
                        generators: list[torch.Generator]) -> TensorDictBase:
    """``size`` sub-episodes of up to ``length`` consecutive steps per member, their first steps drawn
    uniformly WITH replacement from member r's transitions with ``generators[r]``: ``[R, size, length]``,
    with ``"mask"`` marking each one's steps inside its episode (a prefix: a sub-episode that reaches its
    episode's end is shorter).

    ``data`` is a population's memory ``[R, n]`` in slot order whose episodes of ``episode_steps``
    transitions sit in whole blocks (slot ``e * episode_steps + t`` is step t of an episode), as a
    memory whose capacity is a multiple of the episode length keeps them when it is filled an
    episode at a time (one-step transitions)."""
    members, n = data.batch_size
    if n % episode_steps:
        raise ValueError(f"sub-episodes need whole episodes of {episode_steps} transitions in the memory, "
                         f"got {n} transitions")
    start = torch.stack([torch.randint(n, (size,), generator=g, device=g.device) for g in generators])
    offset = torch.arange(length, device=start.device)
    mask = (start % episode_steps).unsqueeze(-1) + offset < episode_steps  # [R, size, length]
    index = torch.where(mask, start.unsqueeze(-1) + offset, start.unsqueeze(-1))  # outside: the first step again
    rows = torch.arange(members, device=start.device).view(members, 1, 1)
    batch = data[rows, index]
    batch.set("mask", mask)
    return batch


def _to_device(state, device: torch.device):
    """A (nested) state dict with its tensors moved to ``device`` (checkpoints load on the CPU);
    mappings are updated in place."""
    if isinstance(state, (torch.Tensor, TensorDictBase)):
        return state.to(device)
    if isinstance(state, dict):  # in place: the mappings carry metadata that TorchRL reads back
        for key, value in state.items():
            state[key] = _to_device(value, device)
        return state
    if isinstance(state, (list, tuple)):
        return type(state)(_to_device(value, device) for value in state)
    return state
