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


STEPS_KEY = "steps_to_next_obs"  # TorchRL's value estimators discount the bootstrap by gamma ** this


def n_step_transitions(batch: TensorDictBase, gamma: float, n: int) -> TensorDictBase:
    """The ``[N, T]`` transitions of ``batch`` (time on dim 1) as n-step transitions, a new TensorDict.

    Transition t keeps its observation and action; its reward becomes
    ``sum_{i<m} gamma^i r_{t+i}``, its next observation (and ``done``, ``terminated``) that
    after step ``t+m-1``, and ``STEPS_KEY`` holds ``m``, where ``m = n`` unless the episode
    ends first (``("next", "done")``, a time limit or a terminal state, or the batch's end):
    TorchRL's TD targets then bootstrap with ``gamma ** m`` (``r + gamma^m * V(s_{t+m})``, no
    bootstrap after a terminal state). ``n = 1`` gives the one-step transitions with ``m = 1``.
    The sums run step by step in float32 in the same order for every car, so a member's
    transitions do not depend on the others in the batch."""
    if n < 1:
        raise ValueError(f"n-step returns need n >= 1, got {n}")
    reward, done = batch["next", "reward"], batch["next", "done"]
    steps = reward.shape[1]
    times = torch.arange(steps, device=reward.device)
    # last[t]: the step whose next state transition t bootstraps from; alive: no episode end yet
    last = times.expand(reward.shape[0], steps).clone()
    total = reward.clone()
    alive = ~done.squeeze(-1)
    for i in range(1, n):
        later = (times + i).clamp_max(steps - 1)
        inside = alive & (times + i < steps)  # [N, T]
        total = torch.where(inside.unsqueeze(-1), total + gamma ** i * reward[:, later], total)
        last = torch.where(inside, later.expand_as(last), last)
        alive = inside & ~done[:, later].squeeze(-1)
    rows = torch.arange(reward.shape[0], device=reward.device).unsqueeze(1)
    out = batch.clone(False)
    following = batch.get("next")[rows, last]
    following.set("reward", total)
    out.set("next", following)
    out.set(STEPS_KEY, (last - times + 1).unsqueeze(-1).to(reward.dtype))
    return out
