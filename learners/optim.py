"""Adam for a population's stacked parameters, with little per-step overhead.

The update is ``torch.optim.Adam``'s (its multi-tensor, non-capturable path, no amsgrad;
with ``weight_decay``, ``torch.optim.AdamW``'s decoupled decay), operation for operation, except that the square root of the second
moment is correctly rounded: torch's float32 ``sqrt`` on CPU calls MKL's vector math, whose
result differs in the last bit from CPU to CPU (it starts from the CPU's approximate
reciprocal square root), so it is the CPU's IEEE 754 square root (the project's kernels) or, where
those cannot be built, taken in float64 and rounded to float32: the correctly rounded root on every
machine either way (``exact_sqrt``). Where torch's own sqrt is
correctly rounded, the update equals ``torch.optim.Adam(foreach=True)`` to the bit
(``tests/test_stacked.py``); ``torch.optim.Adam.step`` spends most of its time on Python
bookkeeping at these sizes (about 0.7 ms a step here against 0.1 ms for the arithmetic).
Adam is element-wise, so one optimiser over stacked parameters is exactly one Adam per member,
and ``freeze`` stops one member without touching the others.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import torch


def exact_sqrt(tensors: list[torch.Tensor], isa: str | None = None) -> list[torch.Tensor]:
    """The correctly rounded square roots of float32 tensors, the same on every CPU.

    By the project's kernels where they load (``learners.kernels``: the CPU's IEEE 754 square
    root, correctly rounded by definition, in one pass; ``isa`` picks a path for tests), else
    ``wide_sqrt``: the same bits.
    """
    from learners import kernels

    if kernels.unavailable_reason() is not None:
        return wide_sqrt(tensors)
    from learners.kernels import ops

    return [ops.sqrt(t, isa) if t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous()
            else wide_sqrt([t])[0] for t in tensors]


def wide_sqrt(tensors: list[torch.Tensor]) -> list[torch.Tensor]:
    """``exact_sqrt`` by torch alone: taken in float64 and rounded to float32. The exact root of a
    float32 number is never within 2^-51 (relative) of a float32 rounding boundary, and float64
    ``sqrt`` errs by less than one float64 unit (2^-52) even where it is computed from an
    approximation, so the rounding always lands on the correctly rounded float32 root."""
    wide = [t.double() for t in tensors]
    torch._foreach_sqrt_(wide)
    return [w.to(t.dtype) for w, t in zip(wide, tensors)]


class MemberAdam:
    """Adam over parameters whose first dimension is the population's members."""

    def __init__(self, params: Iterable[torch.nn.Parameter], lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8, member_dims: Iterable[int] | None = None, weight_decay: float = 0.0):
        """``member_dims``: the members' dimension of each parameter (default: all 0; TorchRL's
        ensembles of Q-networks have theirs at 1, after the ensemble's). ``weight_decay``: each
        step first shrinks the parameters by ``1 - lr * weight_decay`` (AdamW's decoupled decay)."""
        self.params = list(params)
        if not self.params:
            raise ValueError("MemberAdam got no parameters")
        self.member_dims = list(member_dims) if member_dims is not None else [0] * len(self.params)
        if len(self.member_dims) != len(self.params):
            raise ValueError(f"got {len(self.member_dims)} member dims for {len(self.params)} parameters")
        self.lr, self.betas, self.eps = float(lr), (float(betas[0]), float(betas[1])), float(eps)
        self.weight_decay = float(weight_decay)
        self.steps = 0
        self.exp_avg = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]
        self.exp_avg_sq = [torch.zeros_like(p, memory_format=torch.preserve_format) for p in self.params]

    def zero_grad(self, set_to_none: bool = True) -> None:
        for p in self.params:
            p.grad = None

    @torch.no_grad()
    def step(self) -> None:
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in self.params]
        beta1, beta2 = self.betas
        self.steps += 1
        if self.weight_decay:
            torch._foreach_mul_(self.params, 1 - self.lr * self.weight_decay)
        torch._foreach_lerp_(self.exp_avg, grads, 1 - beta1)
        torch._foreach_mul_(self.exp_avg_sq, beta2)
        torch._foreach_addcmul_(self.exp_avg_sq, grads, grads, 1 - beta2)
        bias_correction1 = 1 - beta1 ** self.steps
        bias_correction2_sqrt = math.sqrt(1 - beta2 ** self.steps)
        denom = exact_sqrt(self.exp_avg_sq)
        torch._foreach_div_(denom, bias_correction2_sqrt)
        torch._foreach_add_(denom, self.eps)
        torch._foreach_addcdiv_(self.params, self.exp_avg, denom, -self.lr / bias_correction1)

    @torch.no_grad()
    def zero_member(self, member: int) -> None:
        """Zero ``member``'s moments (see ``learners.base.PhaseRunner.freeze``)."""
        for m, v, dim in zip(self.exp_avg, self.exp_avg_sq, self.member_dims):
            m.select(dim, member).zero_()
            v.select(dim, member).zero_()

    @torch.no_grad()
    def restart(self) -> None:
        """Forget every member's moments and the step count, as a new optimiser would."""
        self.steps = 0
        for t in (*self.exp_avg, *self.exp_avg_sq):
            t.zero_()

    def state_dict(self) -> dict:
        return {"steps": self.steps, "exp_avg": [m.clone() for m in self.exp_avg],
                "exp_avg_sq": [v.clone() for v in self.exp_avg_sq]}

    def load_state_dict(self, state: dict) -> None:
        for key in ("exp_avg", "exp_avg_sq"):
            if [tuple(t.shape) for t in state[key]] != [tuple(p.shape) for p in self.params]:
                raise ValueError(f"optimiser state {key} has shapes {[tuple(t.shape) for t in state[key]]}, "
                                 f"the parameters {[tuple(p.shape) for p in self.params]}")
        self.steps = int(state["steps"])
        for own, saved in ((self.exp_avg, state["exp_avg"]), (self.exp_avg_sq, state["exp_avg_sq"])):
            for target, value in zip(own, saved):
                target.copy_(value)
