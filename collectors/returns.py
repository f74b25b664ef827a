"""Monte-Carlo returns of collected batches, and their flattening into transitions."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.objectives.value.functional import reward2go

RETURN_KEY = "value_target"
TRANSITION_KEYS = ("observation", "action", RETURN_KEY)


def add_monte_carlo_returns(batch: TensorDictBase, gamma: float, key: str = RETURN_KEY) -> TensorDictBase:
    """Write G_t = sum_k gamma^k r_{t+k}, summed to the end of each episode, to ``batch[key]``.

    ``batch`` is ``[N, T]`` with time on dim 1. Sums stop at ``("next", "done")`` (no
    bootstrapping, also at a time-limit truncation); an episode still running at the end of
    the batch is summed to the batch's end, so batches should end where episodes end.
    """
    reward = batch["next", "reward"]
    done = batch["next", "done"]
    # One car at a time: reward2go's arithmetic depends on the batch's shape, and a member of a
    # population must get the returns it gets alone, to the bit.
    returns = [reward2go(reward[i:i + 1], done[i:i + 1], gamma=gamma, time_dim=-2) for i in range(reward.shape[0])]
    batch.set(key, torch.cat(returns) if len(returns) > 1 else returns[0])
    return batch


def episode_transitions(batch: TensorDictBase, keys: tuple[str, ...] = TRANSITION_KEYS) -> TensorDictBase:
    """The ``[N, T]`` batch as ``N * T`` independent transitions with only ``keys``."""
    return batch.select(*keys).reshape(-1)
