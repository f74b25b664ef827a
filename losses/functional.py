"""The loss arithmetic as small pure functions on tensors (the loss modules wrap them).

Shapes: B states, D action dimensions, C candidate actions. Per-dimension terms have shape
[B, D]; the joint form sums them over the action dimensions into [B, 1].
"""

from __future__ import annotations

import math

import torch

RATIO_SPACES = ("linear", "log")
SAMPLE_CENTRES = ("mean", "action")


def per_dimension_or_joint(terms: torch.Tensor, joint: bool) -> torch.Tensor:
    """Log-probabilities or entropies of shape [B, D], summed to [B, 1] if ``joint``."""
    return terms.sum(-1, keepdim=True) if joint else terms


def squared_error(prediction: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean of (target - prediction)^2: the Monte-Carlo critic's loss."""
    return (target - prediction).pow(2).mean()


def clip_bounds(clip_epsilon: float, ratio_space: str) -> tuple[float, float]:
    """Where the ratio is clipped: [1 - eps, 1 + eps] or [log(1 - eps), log(1 + eps)]."""
    if ratio_space == "linear":
        return 1.0 - clip_epsilon, 1.0 + clip_epsilon
    if ratio_space == "log":
        return math.log(1.0 - clip_epsilon), math.log(1.0 + clip_epsilon)
    raise ValueError(f"ratio_space must be one of {RATIO_SPACES}, got {ratio_space!r}")


def ppo_ratio(log_prob: torch.Tensor, old_log_prob: torch.Tensor, ratio_space: str) -> torch.Tensor:
    """p = exp(logp - logp_old) in linear space, p = logp - logp_old in log space."""
    log_ratio = log_prob - old_log_prob
    return log_ratio.exp() if ratio_space == "linear" else log_ratio


def clipped_surrogate(ratio: torch.Tensor, advantage: torch.Tensor, clip_epsilon: float,
                      ratio_space: str) -> tuple[torch.Tensor, torch.Tensor]:
    """min(p A, clip(p, low, high) A), elementwise, and where the clipped term was taken.

    ``advantage`` broadcasts against ``ratio`` ([B, 1] against [B, D]). Returns the
    objective (to maximise) and a boolean mask of the entries whose gradient was clipped.
    """
    low, high = clip_bounds(clip_epsilon, ratio_space)
    unclipped = ratio * advantage
    clipped = ratio.clamp(low, high) * advantage
    return torch.minimum(unclipped, clipped), clipped < unclipped


def approx_kl(log_prob: torch.Tensor, old_log_prob: torch.Tensor) -> torch.Tensor:
    """Mean of (r - 1) - log r, r = exp(logp - logp_old): a low-variance KL(old || new) estimate."""
    log_ratio = log_prob - old_log_prob
    return (log_ratio.exp() - 1 - log_ratio).mean()


def spg_candidates(action: torch.Tensor, mean: torch.Tensor, noise: torch.Tensor,
                   temperature: float, centre: str = "mean") -> torch.Tensor:
    """SPG's candidate actions, [B, 2 + K, D]: the stored action, the policy mean, then K
    perturbations clip(centre + temperature * noise, -1, 1), ``noise`` ~ N(0, I) of shape [B, K, D].

    ``centre`` is ``"mean"`` (the reference implementation) or ``"action"`` (the paper's text).
    """
    if centre not in SAMPLE_CENTRES:
        raise ValueError(f"centre must be one of {SAMPLE_CENTRES}, got {centre!r}")
    base = mean if centre == "mean" else action
    samples = (base.unsqueeze(-2) + temperature * noise).clamp(-1.0, 1.0)
    return torch.cat([action.unsqueeze(-2), mean.unsqueeze(-2), samples], dim=-2)


def best_candidate(candidates: torch.Tensor, scores: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The highest-scoring candidate per state (the first one on ties) and its index.

    ``candidates`` [B, C, D], ``scores`` [B, C]; returns ([B, D], [B]).
    """
    index = scores.argmax(dim=-1)
    target = candidates.gather(-2, index[:, None, None].expand(-1, 1, candidates.shape[-1])).squeeze(-2)
    return target, index


def weighted_log_likelihood(log_prob: torch.Tensor, weight: torch.Tensor | None) -> torch.Tensor:
    """Mean of weight * log pi(target | s) (SPG: no weight; SPG-p: weight = Q gain, [B, 1])."""
    return (log_prob if weight is None else weight * log_prob).mean()
