"""The loss arithmetic as small pure functions on tensors (the loss modules wrap them).

Shapes: B states, D action dimensions, C candidate actions. Per-dimension terms have shape
[B, D]; the joint form sums them over the action dimensions into [B, 1]. Every function also
takes leading batch dimensions (a population's members: [R, B, ...]); the reductions take
``members=True`` to average over everything but the first dimension, giving one value per
member ([R]) instead of one scalar.
"""

from __future__ import annotations

import math

import torch

RATIO_SPACES = ("linear", "log")
SAMPLE_CENTRES = ("mean", "action")
ALIGN = 32  # elements: a multiple of every CPU vector loop's step (2 x 16 floats with AVX-512)


def per_member(fn, values: torch.Tensor) -> torch.Tensor:
    """``fn(values)`` for an element-wise ``fn``, computed so that member r's results (first
    dimension) do not depend on how many members share the tensor.

    CPU kernels of functions such as exp, log, tanh and softplus compute most elements in a
    vector loop and the last few (a tensor's tail) in scalar code that rounds differently. In
    a stacked tensor a member's last elements would fall in the vector loop or in the tail
    depending on the members after it. Padding each member's elements to a multiple of
    ``ALIGN`` (with ones) leaves no tail, so every element takes the vector path, alone or in
    a population, in the forward and the backward pass.
    """
    n = values[0].numel()
    if n % ALIGN == 0:
        return fn(values)
    flat = torch.nn.functional.pad(values.reshape(values.shape[0], n), (0, (-n) % ALIGN), value=1.0)
    return fn(flat)[:, :n].reshape(values.shape)


_LOOP_BYTES: int | None = None


def loop_bytes() -> int:
    """The bytes one iteration of ATen's vector loop takes (two vectors): 128 with its AVX-512 kernels,
    64 with its AVX2 (or generic) ones. Elements before the last whole iteration take the vector code,
    the rest (the tail) the scalar code, which rounds some functions (softplus) differently."""
    global _LOOP_BYTES
    if _LOOP_BYTES is None:
        _LOOP_BYTES = 128 if "512" in torch.backends.cpu.get_cpu_capability() else 64
    return _LOOP_BYTES


def as_alone(fn, values: torch.Tensor) -> torch.Tensor:
    """``fn(values)`` for an element-wise ``fn``, each member's results (first dimension) computed as a solo
    run computes them on that member's tensor alone, however many members share it.

    Alone, a member's first elements fall in ATen's vector loop and its last ``n % step`` elements (its
    tail; all of them when it holds fewer than ``step``) in its scalar code (``loop_bytes``). Stacked, its
    elements would fall in one or the other by their place among the other members' (an acting step's
    softplus on ``[R, 2]``: scalar alone, vector from eight members on). Here every member's vector part
    is computed in one contiguous call (a multiple of the step each: all vector) and every tail in one
    strided call (never vectorised: scalar), which is what a solo run does. ``per_member`` instead makes
    every element take the vector code, alone or not (where the solo run goes through it too). ``fn`` must be
    one ATen element-wise kernel (softplus, tanh): a composite would make its own contiguous temporaries."""
    members = values.shape[0]
    n = values[0].numel() if members else 0
    step = loop_bytes() // values.element_size()
    head = n - n % step
    if not n or values.device.type != "cpu":
        return fn(values)
    flat = values.reshape(members, n)
    if head == n:
        return fn(flat.contiguous()).reshape(values.shape)
    parts = []
    if head:
        parts.append(fn(flat[:, :head].contiguous()))
    tail = torch.empty(members, n - head, 2, dtype=values.dtype, device=values.device)
    tail[..., 0] = flat[:, head:]
    parts.append(fn(tail[..., 0]))  # a strided input: ATen's scalar loop for every element
    return torch.cat(parts, 1).reshape(values.shape) if head else parts[0].reshape(values.shape)


def per_dimension_or_joint(terms: torch.Tensor, joint: bool) -> torch.Tensor:
    """Log-probabilities or entropies of shape [B, D], summed to [B, 1] if ``joint``."""
    return terms.sum(-1, keepdim=True) if joint else terms


def mean(values: torch.Tensor, members: bool = False) -> torch.Tensor:
    """The mean of ``values``: a scalar, or one per member (first dimension) if ``members``."""
    return values.reshape(values.shape[0], -1).mean(-1) if members else values.mean()


def squared_error(prediction: torch.Tensor, target: torch.Tensor, members: bool = False) -> torch.Tensor:
    """Mean of (target - prediction)^2: the Monte-Carlo critic's loss."""
    return mean((target - prediction).pow(2), members)


def clip_bounds(clip_epsilon: float, ratio_space: str) -> tuple[float, float]:
    """Where the ratio is clipped: [1 - eps, 1 + eps] or [log(1 - eps), log(1 + eps)]."""
    if ratio_space == "linear":
        return 1.0 - clip_epsilon, 1.0 + clip_epsilon
    if ratio_space == "log":
        return math.log(1.0 - clip_epsilon), math.log(1.0 + clip_epsilon)
    raise ValueError(f"ratio_space must be one of {RATIO_SPACES}, got {ratio_space!r}")


def ppo_ratio(log_prob: torch.Tensor, old_log_prob: torch.Tensor, ratio_space: str,
              members: bool = False) -> torch.Tensor:
    """p = exp(logp - logp_old) in linear space, p = logp - logp_old in log space."""
    log_ratio = log_prob - old_log_prob
    if ratio_space != "linear":
        return log_ratio
    return per_member(torch.exp, log_ratio) if members else log_ratio.exp()


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


def approx_kl(log_prob: torch.Tensor, old_log_prob: torch.Tensor, members: bool = False) -> torch.Tensor:
    """Mean of (r - 1) - log r, r = exp(logp - logp_old): a low-variance KL(old || new) estimate."""
    log_ratio = log_prob - old_log_prob
    ratio = per_member(torch.exp, log_ratio) if members else log_ratio.exp()
    return mean(ratio - 1 - log_ratio, members)


def spg_candidates(action: torch.Tensor, policy_mean: torch.Tensor, noise: torch.Tensor,
                   temperature: float | torch.Tensor, centre: str = "mean") -> torch.Tensor:
    """SPG's candidate actions, [B, 2 + K, D]: the stored action, the policy mean, then K
    perturbations clip(centre + temperature * noise, -1, 1), ``noise`` ~ N(0, I) of shape [B, K, D].

    ``centre`` is ``"mean"`` (the reference implementation) or ``"action"`` (the paper's text).
    ``temperature`` is a number or a tensor broadcasting against ``noise`` (one per member).
    """
    if centre not in SAMPLE_CENTRES:
        raise ValueError(f"centre must be one of {SAMPLE_CENTRES}, got {centre!r}")
    base = policy_mean if centre == "mean" else action
    samples = (base.unsqueeze(-2) + temperature * noise).clamp(-1.0, 1.0)
    return torch.cat([action.unsqueeze(-2), policy_mean.unsqueeze(-2), samples], dim=-2)


def best_candidate(candidates: torch.Tensor, scores: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The highest-scoring candidate per state (the first one on ties) and its index.

    ``candidates`` [..., B, C, D], ``scores`` [..., B, C]; returns ([..., B, D], [..., B]).
    """
    index = scores.argmax(dim=-1)
    picks = index[..., None, None].expand(*index.shape, 1, candidates.shape[-1])
    return candidates.gather(-2, picks).squeeze(-2), index


def weighted_log_likelihood(log_prob: torch.Tensor, weight: torch.Tensor | None,
                            members: bool = False) -> torch.Tensor:
    """Mean of weight * log pi(target | s) (SPG: no weight; SPG-p: weight = Q gain, [B, 1])."""
    return mean(log_prob if weight is None else weight * log_prob, members)


def symlog(x: torch.Tensor) -> torch.Tensor:
    """sign(x) log(1 + |x|)."""
    return x.sign() * per_member(torch.log1p, x.abs())


def symexp(x: torch.Tensor) -> torch.Tensor:
    """sign(x) (exp(|x|) - 1), the inverse of ``symlog``."""
    return x.sign() * per_member(torch.expm1, x.abs())
