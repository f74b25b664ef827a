"""Monte-Carlo returns of collected batches, and their flattening into transitions."""

from __future__ import annotations

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
    batch.set(key, reward2go(reward, done, gamma=gamma, time_dim=-2))
    return batch


def episode_transitions(batch: TensorDictBase, keys: tuple[str, ...] = TRANSITION_KEYS) -> TensorDictBase:
    """The ``[N, T]`` batch as ``N * T`` independent transitions with only ``keys``."""
    return batch.select(*keys).reshape(-1)
