"""Proportional prioritised replay in plain PyTorch, as a TorchRL ``Sampler``.

TorchRL's ``PrioritizedSampler`` needs its compiled segment trees, which do not load with the
pinned CPU torch build (``SumSegmentTreeFp32 is not available``). This sampler keeps the same
definitions (Schaul et al.'s proportional variant, as TorchRL implements it):

- a transition's stored priority is ``(p + eps) ** alpha`` for its raw priority ``p``
  (``|TD error|``); new transitions get the largest raw priority seen so far (1 at first);
- it is drawn with probability ``P(i) = (p_i + eps) ** alpha / sum_j (p_j + eps) ** alpha``;
- its importance weight is ``(N P(i)) ** -beta / max_j (N P(j)) ** -beta = (P(i) / min_j P(j)) ** -beta``.

Sampling is a cumulative sum and a binary search over the stored priorities (O(N) per call, no
trees): at replay memories of 10^4 to 10^5 transitions that costs tens of microseconds, well
below a gradient step. It plugs into a ``TensorDictReplayBuffer`` like any sampler (``sample``
returns ``(index, {"priority_weight": weight})``, ``update_priority`` takes new raw priorities),
and for a population (``members=R``, one memory per member in each storage slot) ``sample_members``
draws each member's indices from its own priorities with its own generator.
"""

from __future__ import annotations


import torch
from torchrl.data.replay_buffers.samplers import Sampler

WEIGHT_KEY = "priority_weight"  # where TorchRL's losses look for importance weights


class ProportionalSampler(Sampler):
    """Proportional prioritised sampling with replacement over ``capacity`` slots.

    Args:
        capacity: the storage's capacity (slots).
        alpha: priority exponent (0: uniform sampling).
        beta: importance-sampling exponent (0: no correction, 1: full).
        eps: added to every raw priority, so that no stored transition has probability 0.
        members: None for one memory; R for a population's memories (priorities ``[slot, R]``).
        generator: the ``torch.Generator`` of ``sample`` (one memory; None: torch's global one).
    """

    def __init__(self, capacity: int, alpha: float, beta: float, eps: float = 1e-6, members: int | None = None,
                 generator: torch.Generator | None = None):
        super().__init__()
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        if alpha < 0 or not 0 <= beta <= 1 or eps <= 0:
            raise ValueError(f"need alpha >= 0, 0 <= beta <= 1 and eps > 0; got {alpha}, {beta}, {eps}")
        self.capacity, self.alpha, self.beta, self.eps = capacity, float(alpha), float(beta), float(eps)
        self.members = members
        self.generator = generator
        width = members if members is not None else 1
        self._powered = torch.zeros(capacity, width, dtype=torch.float64)  # (p + eps) ** alpha; 0: empty slot
        self._max = torch.ones(width, dtype=torch.float64)  # largest raw priority so far, per member

    # -------------------------------------------------------------- the Sampler interface
    @property
    def default_priority(self) -> float:
        return float(self._max.max())

    def extend(self, index: torch.Tensor) -> None:
        """New transitions in slots ``index``: the largest raw priority so far (per member)."""
        index = torch.as_tensor(index, dtype=torch.long).reshape(-1)
        self._powered[index] = ((self._max + self.eps) ** self.alpha).to(self._powered.dtype)

    def add(self, index: int) -> None:
        self.extend(torch.as_tensor([index]))

    def sample(self, storage, batch_size: int) -> tuple[torch.Tensor, dict]:
        """One memory: ``batch_size`` slot indices and their importance weights."""
        if self.members is not None:
            raise RuntimeError("a population's sampler draws per member: use sample_members")
        index, weight = self.sample_members(len(storage), batch_size, [self.generator])
        return index[0], {WEIGHT_KEY: weight[0].float()}

    @torch.no_grad()
    def update_priority(self, index, priority, *, storage=None) -> None:
        """Raw priorities (``|TD error|``) of sampled transitions: ``index`` and ``priority`` of shape
        ``[B]`` for one memory, ``[R, B]`` for a population. Repeated indices keep the last value."""
        index = torch.as_tensor(index, dtype=torch.long)
        priority = torch.as_tensor(priority, dtype=torch.float64).detach().cpu().reshape(index.shape)
        if not torch.isfinite(priority).all() or (priority < 0).any():
            raise ValueError("priorities must be finite and non-negative")
        if index.ndim == 1:
            index, priority = index.unsqueeze(0), priority.unsqueeze(0)
        if index.shape[0] != self._powered.shape[1]:
            raise ValueError(f"got priorities for {index.shape[0]} member(s), the sampler has {self._powered.shape[1]}")
        members = torch.arange(index.shape[0]).unsqueeze(1).expand_as(index)
        self._powered[index.cpu(), members] = (priority + self.eps) ** self.alpha
        self._max = torch.maximum(self._max, priority.max(1).values)

    def state_dict(self) -> dict:
        return {"powered": self._powered.clone(), "max": self._max.clone()}

    def load_state_dict(self, state_dict: dict) -> None:
        if tuple(state_dict["powered"].shape) != tuple(self._powered.shape):
            raise ValueError(f"saved priorities have shape {tuple(state_dict['powered'].shape)}, "
                             f"this sampler {tuple(self._powered.shape)}")
        self._powered.copy_(state_dict["powered"])
        self._max.copy_(state_dict["max"])

    def _empty(self) -> None:
        self._powered.zero_()
        self._max.fill_(1.0)

    def dumps(self, path) -> None:
        """Not a file writer: the sampler's state is its ``state_dict``, which a run's checkpoint holds
        (engine/checkpoint.py writes every file of a run, through the file door)."""
        raise NotImplementedError("PrioritisedSampler is saved with the run's checkpoint (its state_dict), not by "
                                  "ReplayBuffer.dumps")

    def loads(self, path) -> None:
        """Not a file reader: see ``dumps``."""
        raise NotImplementedError("PrioritisedSampler is restored from the run's checkpoint (load_state_dict), not by "
                                  "ReplayBuffer.loads")

    # ----------------------------------------------------------------------- populations
    @torch.no_grad()
    def sample_members(self, filled: int, batch_size: int, generators) -> tuple[torch.Tensor, torch.Tensor]:
        """Indices ``[R, batch_size]`` into the first ``filled`` slots, member r's drawn from its
        own priorities with ``generators[r]``, and their importance weights ``[R, batch_size]``."""
        if filled < 1:
            raise RuntimeError("cannot sample from an empty memory")
        powered = self._powered[:filled].T  # [R, n]
        if len(generators) != powered.shape[0]:
            raise ValueError(f"got {len(generators)} generators for {powered.shape[0]} member(s)")
        total = powered.cumsum(1)
        mass = torch.stack([torch.rand(batch_size, generator=g, dtype=torch.float64,
                                       device=g.device if g is not None else None).cpu() for g in generators])
        index = torch.searchsorted(total, mass * total[:, -1:], right=True).clamp_max_(filled - 1)
        chosen = powered.gather(1, index)
        weight = (chosen / powered.min(1, keepdim=True).values) ** -self.beta
        return index, weight
