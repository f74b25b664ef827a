"""The torch side of ``learners.kernels``: batched products, column sums and the stacked linear
layer's autograd, all by the fixed FMA chains of ``gemm.cpp``. Tensors must be float32 on the CPU."""

from __future__ import annotations

import torch

from learners.kernels import KernelError, _isa_code, _lib


def _check(name: str, t: torch.Tensor, dim: int) -> None:
    if t.dtype != torch.float32 or t.device.type != "cpu" or t.dim() != dim:
        raise TypeError(f"{name} must be a {dim}-d float32 CPU tensor, got {t.dim()}-d {t.dtype} on {t.device}")


def bmm(a: torch.Tensor, b: torch.Tensor, bias: torch.Tensor | None = None, isa: str | None = None) -> torch.Tensor:
    """``a [R, M, K] @ b [R, K, N] (+ bias [R, N])`` -> ``[R, M, N]``, any strides, by the fixed
    FMA chains (``isa`` picks a path for tests; every path gives the same bits). Not autograd-aware."""
    _check("a", a, 3)
    _check("b", b, 3)
    R, M, K = a.shape
    if b.shape[0] != R or b.shape[1] != K:
        raise ValueError(f"cannot multiply {tuple(a.shape)} by {tuple(b.shape)}")
    if bias is not None:
        _check("bias", bias, 2)
        if tuple(bias.shape) != (R, b.shape[2]):
            raise ValueError(f"bias must be {(R, b.shape[2])}, got {tuple(bias.shape)}")
    return _product(a, a.stride(), b, b.stride(), b.shape[2], bias, _isa_code(isa))


def _product(a: torch.Tensor, sa: tuple, b: torch.Tensor, sb: tuple, n: int, bias: torch.Tensor | None,
             code: int) -> torch.Tensor:
    """``bmm`` without checks, on A's and B's element strides (``sb`` may describe a transpose of
    ``b``'s storage, so no view is made): the layers' hot path."""
    R, M, K = a.shape
    out = torch.empty(R, M, n, dtype=torch.float32)
    if bias is None:
        bias_ptr, b0, b1 = None, 0, 0
    else:
        bias_ptr, (b0, b1) = bias.data_ptr(), bias.stride()
    if _gemm()(code, R, M, n, K, a.data_ptr(), sa[0], sa[1], sa[2], b.data_ptr(), sb[0], sb[1], sb[2],
               out.data_ptr(), M * n, n, 1, bias_ptr, b0, b1):
        raise KernelError(f"racing_gemm refused the instruction set code {code}")
    return out


_GEMM = None


def _gemm():
    global _GEMM
    if _GEMM is None:
        _GEMM = _lib().racing_gemm
    return _GEMM


def sqrt(x: torch.Tensor, isa: str | None = None) -> torch.Tensor:
    """The correctly rounded square roots of a contiguous float32 tensor (the CPU's IEEE 754 sqrt;
    every ``isa`` path gives the same bits, torch's float32 sqrt need not)."""
    if x.dtype != torch.float32 or x.device.type != "cpu" or not x.is_contiguous():
        raise TypeError(f"x must be a contiguous float32 CPU tensor, got {x.dtype} on {x.device}")
    root = torch.empty_like(x)
    code = _isa_code(isa)
    if _lib().racing_sqrt(code, x.numel(), x.data_ptr(), root.data_ptr()):
        raise KernelError(f"racing_sqrt refused the instruction set code {code}")
    return root


def colsum(x: torch.Tensor) -> torch.Tensor:
    """``x [R, M, N]`` summed over M in row order from zero -> ``[R, N]`` (a bias gradient)."""
    _check("x", x, 3)
    R, M, N = x.shape
    out = torch.empty(R, N, dtype=torch.float32)
    s = x.stride()
    _lib().racing_colsum(R, M, N, x.data_ptr(), s[0], s[1], s[2], out.data_ptr(), N)
    return out


def _forward(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``x @ weight^T + bias``: B is weight's transpose, read through swapped strides."""
    return _product(x, x.stride(), weight, _swapped(weight.stride()), weight.shape[1], bias, _isa_code(None))


def _input_grad(grad: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    return _product(grad, grad.stride(), weight, weight.stride(), weight.shape[2], None, _isa_code(None))


def _weight_grad(grad: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """``grad^T @ x``: A is grad's transpose (a view of its storage)."""
    return _product(grad.transpose(1, 2), _swapped(grad.stride()), x, x.stride(), x.shape[2], None,
                    _isa_code(None))


def _swapped(s: tuple) -> tuple:
    return s[0], s[2], s[1]


class _Linear(torch.autograd.Function):
    """``x [R, M, in] @ weight[R, out, in]^T + bias[R, out]`` with its gradients by the kernels,
    eagerly (through ctypes; torch.compile traces the ``racing::fma_linear`` operator instead).
    A forward with ``ctx`` (no separate ``setup_context``): torch then skips binding the arguments
    by signature, a few microseconds a call (docs/speed.md)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        return _forward(x, weight, bias)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return _gradients(ctx, grad, _input_grad, _weight_grad, colsum)


def _save_inputs(ctx, inputs, output) -> None:
    x, weight, _ = inputs
    ctx.save_for_backward(x, weight)


def _gradients(ctx, grad: torch.Tensor, input_grad, weight_grad, column_sum) -> tuple:
    """The gradients the layer's inputs need, by the given products (the ctypes calls eagerly,
    the ``racing::`` operators in compiled graphs)."""
    x, weight = ctx.saved_tensors
    need_x, need_w, need_b = ctx.needs_input_grad
    return (input_grad(grad, weight) if need_x else None, weight_grad(grad, x) if need_w else None,
            column_sum(grad) if need_b else None)


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """R stacked linear layers, ``[R, M, in] -> [R, M, out]``, forward and backward by the fixed
    FMA chains: the input gradient's chains run over the outputs in order, the weight gradient's
    and the bias gradient's over the rows in order. Without autograd (no input needs a gradient,
    or gradients are off), one product."""
    if torch.compiler.is_compiling():
        return torch.ops.racing.fma_linear(x, weight, bias)  # autograd and vmap registered below
    if torch.is_grad_enabled() and (x.requires_grad or weight.requires_grad or bias.requires_grad):
        return _Linear.apply(x, weight, bias)
    return _forward(x, weight, bias)


# The same computations as torch operators, for graphs that torch.compile traces (``compile=true``).
@torch.library.custom_op("racing::fma_linear", mutates_args=())
def _linear_op(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    return _forward(x, weight, bias)


@_linear_op.register_fake
def _(x, weight, bias):
    return x.new_empty(x.shape[0], x.shape[1], weight.shape[1])


@torch.library.custom_op("racing::fma_input_grad", mutates_args=())
def _input_grad_op(grad: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    return _input_grad(grad, weight)


@_input_grad_op.register_fake
def _(grad, weight):
    return grad.new_empty(grad.shape[0], grad.shape[1], weight.shape[2])


@torch.library.custom_op("racing::fma_weight_grad", mutates_args=())
def _weight_grad_op(grad: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    return _weight_grad(grad, x)


@_weight_grad_op.register_fake
def _(grad, x):
    return grad.new_empty(grad.shape[0], grad.shape[2], x.shape[2])


@torch.library.custom_op("racing::fma_colsum", mutates_args=())
def _colsum_op(x: torch.Tensor) -> torch.Tensor:
    return colsum(x)


@_colsum_op.register_fake
def _(x):
    return x.new_empty(x.shape[0], x.shape[2])


def _merge(t: torch.Tensor, dim: int | None, size: int) -> torch.Tensor:
    """A vmapped operand ``[..., R, ...]`` with its vmap dimension ``dim`` (None: shared) folded into
    the members': ``[size * R, ...]``. Members never mix, so this is exactly ``size`` calls."""
    t = t.movedim(dim, 0) if dim is not None else t.unsqueeze(0).expand(size, *t.shape)
    return t.reshape(size * t.shape[1], *t.shape[2:])


def _vmap_rule(op):
    def rule(info, in_dims, *args):
        out = op(*(_merge(a, d, info.batch_size) for a, d in zip(args, in_dims)))
        return out.reshape(info.batch_size, -1, *out.shape[1:]), 0
    return rule


for _op in (_linear_op, _input_grad_op, _weight_grad_op, _colsum_op):
    _op.register_vmap(_vmap_rule(_op))


def _linear_backward(ctx, grad):
    return _gradients(ctx, grad, torch.ops.racing.fma_input_grad, torch.ops.racing.fma_weight_grad,
                      torch.ops.racing.fma_colsum)


_linear_op.register_autograd(_linear_backward, setup_context=_save_inputs)
