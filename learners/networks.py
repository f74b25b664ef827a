"""The paper's networks for a population: R independent members in one module.

Each layer's parameters carry a leading member dimension (weight ``[R, out, in]``, bias
``[R, out]``) and one ``torch.baddbmm`` evaluates all members at once on inputs of shape
``[R, ..., in]``. Members never mix: member r's outputs depend only on its own parameters and
inputs, its gradients only on its own loss terms (sum the members' losses, never average
them), and Adam is element-wise, so one optimiser over the stacked parameters is exactly one
Adam per member. Use ``torch.optim.Adam(foreach=True)``: the fused CPU kernel rounds the
last elements of a tensor (the tail of its vector loop) differently, so a member's update
would depend on its position in the stacked tensor.

Bit for bit: member r of a population equals a population of one made from the same seed
(forward, gradients, Adam steps; ``tests/test_stacked.py``), in every numerics mode
(``engine/numerics.py``). In the default mode, ``fma``, the products (forward and both
gradients) run in the project's kernels (``learners.kernels``), where this holds by
construction; in the other two they are ``torch.baddbmm`` (MKL), and the rest of this paragraph
applies. No matrix product has a dimension of one: a one-unit layer
computes as two units (see ``StackedLinear.forward``), because MKL's batched products take
matrix-vector paths there whose rounding depends on the number of members on AVX-512 CPUs.
A member's saved weights load into the solo networks of ``learners.solo`` and compute the same function to float
rounding (``F.linear`` and ``bmm`` accumulate in other orders), so training compares a
population with populations of one, and the solo networks serve evaluation.

Elementwise functions (activations, the heads' tanh and softplus, the policy's logarithms) go
through ``losses.functional.per_member``: CPU kernels round a tensor's last elements
differently, and without it a member's results would depend on the members after it.

Initialisation draws each member's Glorot-uniform kernels from that member's own
``torch.Generator``, in layer order (actor body, heads, then critic when both are built from
the same generator), so a member's initial weights depend on its seed alone.

"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence

import torch
from torch import nn

from tensordict.nn import NormalParamExtractor

from learners import kernels
from learners.kernels import ops as kernel_ops
from losses.functional import ALIGN, as_alone, per_member


class StackedLinear(nn.Module):
    """R independent ``nn.Linear(in_features, out_features)`` layers."""

    def __init__(self, members: int, in_features: int, out_features: int):
        super().__init__()
        if members < 1:
            raise ValueError(f"a population needs at least one member, got {members}")
        self.weight = nn.Parameter(torch.empty(members, out_features, in_features))
        self.bias = nn.Parameter(torch.zeros(members, out_features))

    @property
    def members(self) -> int:
        return self.weight.shape[0]

    def reset_parameters(self, generators: Sequence[torch.Generator | None]) -> None:
        """Glorot-uniform kernels (member r's from ``generators[r]``) and zero biases."""
        if len(generators) != self.members:
            raise ValueError(f"got {len(generators)} generators for {self.members} members")
        with torch.no_grad():
            for weight, generator in zip(self.weight, generators):
                nn.init.xavier_uniform_(weight, generator=generator)
            self.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``[R, ..., in] -> [R, ..., out]``."""
        return stacked_linear(x, self.weight, self.bias)


def stacked_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """``StackedLinear``'s computation with the given parameters (weight ``[R, out, in]``, bias
    ``[R, out]``): ``[R, ..., in] -> [R, ..., out]``."""
    members = weight.shape[0]
    if x.shape[0] != members:
        raise ValueError(f"input has {x.shape[0]} members on its first dimension, this layer {members}")
    flat = x.reshape(members, -1, x.shape[-1])
    units = weight.shape[1]
    if kernels.active() and flat.device.type == "cpu" and flat.dtype == weight.dtype == torch.float32:
        # numerics=fma: the project's products, each element one fixed chain of FMAs
        out = kernel_ops.linear(flat, weight, bias)
        return out.reshape(*x.shape[:-1], out.shape[-1])
    if units == 1:
        # A one-unit layer computes as two units, the second all zeros, and drops it.
        # With a matrix dimension of 1 (this layer's forward and its weight gradient), the
        # batched matrix product takes matrix-vector paths whose rounding depends on the
        # number of members on some CPUs (seen with AVX-512); without one, it does not.
        weight = torch.cat([weight, weight.new_zeros(weight.shape)], dim=1)
        bias = torch.cat([bias, bias.new_zeros(bias.shape)], dim=1)
    out = torch.baddbmm(bias.unsqueeze(1), flat, weight.transpose(1, 2))[..., :units]
    return out.reshape(*x.shape[:-1], out.shape[-1])


class _Tanh(torch.autograd.Function):
    """tanh as 2 sigmoid(2x) - 1 (float32 ``torch.tanh`` is about 3x slower than sigmoid in CPU
    builds that do not vectorise it), with tanh's own one-pass backward, 1 - y^2."""

    generate_vmap_rule = True  # usable under torch.vmap (TorchRL's losses vmap over Q-networks)

    @staticmethod
    def forward(x: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(x * 2.0).mul(2.0).sub(1.0)  # not in place: vmap's rule traces it with autograd

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(output)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


class _EagerTanh(torch.autograd.Function):
    """``_Tanh`` outside torch.vmap and torch.compile: a forward with ``ctx``, which torch calls
    without binding its arguments by signature (a few microseconds a call)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor) -> torch.Tensor:
        y = torch.sigmoid(x * 2.0).mul_(2.0).sub_(1.0)  # _Tanh's values
        ctx.save_for_backward(y)
        return y

    backward = _Tanh.backward


def fast_tanh(x: torch.Tensor) -> torch.Tensor:
    """tanh(x) to within 2.4e-7 (absolute), about 1.6x faster than ``torch.tanh`` forward and
    backward on minibatch-sized float32 inputs here (``speed/population_speed.py``)."""
    if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
        return _Tanh.apply(x)
    if not (torch.is_grad_enabled() and x.requires_grad):  # no graph to record: the values alone, without
        return torch.sigmoid(x * 2.0).mul_(2.0).sub_(1.0)  # the autograd function's call (_EagerTanh's arithmetic)
    return _EagerTanh.apply(x)


_STACKED_ACTIVATIONS = {"tanh": fast_tanh, "relu": torch.relu, "elu": nn.functional.elu}


class StackedMLP(nn.Module):
    """``learners.solo.MLP`` for R members.

    Inputs ``[R, ..., in]`` are flattened to ``[R, N, in]`` rows, and N is padded with zero
    rows to a multiple of ``row_multiple`` so that every hidden activation holds a multiple
    of ``losses.functional.ALIGN`` elements per member: then element-wise kernels treat every
    member alike without copying (``per_member``), alone or in a population. Rows never mix;
    the padding rows are dropped from the output.
    """

    def __init__(self, members: int, sizes: Sequence[int], activation: str = "tanh", linear_output: bool = False):
        super().__init__()
        self.layers = nn.ModuleList(StackedLinear(members, a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.activation = _STACKED_ACTIVATIONS[activation]
        self.members = members
        self.linear_output = linear_output
        widths = sizes[1:-1] if linear_output else sizes[1:]
        self.row_multiple = math.lcm(*(ALIGN // math.gcd(ALIGN, w) for w in widths)) if widths else 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        rows, shape = _pad_rows(x, self.row_multiple)
        return _unpad_rows(self.forward_rows(rows), shape)

    def forward_with(self, x: torch.Tensor, parameters: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
        """``forward`` with other parameters (see ``forward_rows_with``)."""
        rows, shape = _pad_rows(x, self.row_multiple)
        return _unpad_rows(self.forward_rows_with(rows, parameters), shape)

    def forward_rows(self, x: torch.Tensor) -> torch.Tensor:
        """``[R, N, in] -> [R, N, out]`` for N a multiple of ``row_multiple``."""
        return self.forward_rows_with(x, [(layer.weight, layer.bias) for layer in self.layers])

    def forward_rows_with(self, x: torch.Tensor, parameters: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
        """``forward_rows`` with other parameters, a (weight, bias) pair per layer whose leading
        dimension may hold any number of stacked networks (``[S, out, in]``, ``[S, out]``; ``x``
        ``[S, N, in]``): what one network of this shape computes for each, in one pass."""
        last = len(parameters) - 1
        for i, (weight, bias) in enumerate(parameters):
            x = stacked_linear(x, weight, bias)
            if not (self.linear_output and i == last):
                x = per_member(self.activation, x)
        return x


class MemberNormalParamExtractor(NormalParamExtractor):
    """tensordict's ``NormalParamExtractor`` (``biased_softplus_1.0`` scale, ``scale_lb``) for stacked members:
    the softplus computed ``as_alone`` (``losses.functional``), so that a member's scale is its solo run's
    whatever the population's size (an acting step's ``[R, 1, 2]`` took ATen's scalar softplus alone and its
    vector one from eight members on, which round differently)."""

    def __init__(self, scale_lb: float = 1e-4):
        super().__init__(scale_mapping="biased_softplus_1.0", scale_lb=scale_lb)

    def forward(self, *tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
        tensor, *others = tensors
        loc, scale = tensor.chunk(2, -1)
        mapping = self.scale_mapping
        scale = (as_alone(nn.functional.softplus, scale + mapping.bias) + mapping.min_val).clamp_min(self.scale_lb)
        return (loc, scale, *others)


def _pad_rows(x: torch.Tensor, multiple: int) -> tuple[torch.Tensor, torch.Size]:
    """``[R, ..., F]`` -> ``[R, N, F]`` with zero rows added to make N a multiple of ``multiple``."""
    shape = x.shape
    x = x.reshape(shape[0], -1, shape[-1])
    pad = (-x.shape[1]) % multiple
    return (nn.functional.pad(x, (0, 0, 0, pad)) if pad else x), shape


def _unpad_rows(x: torch.Tensor, shape: torch.Size) -> torch.Tensor:
    """The inverse of ``_pad_rows`` for an output of ``x.shape[-1]`` features."""
    rows = math.prod(shape[1:-1])
    if x.shape[1] != rows:
        x = x[:, :rows]
    return x.reshape(*shape[:-1], x.shape[-1])


def wide_std(var: torch.Tensor, eps: float) -> torch.Tensor:
    """``sqrt(var + eps)`` taken in float64 and rounded to ``var``'s dtype: correctly rounded (as
    ``learners.optim.exact_sqrt``), so it does not depend on the CPU's vector math."""
    return (var.double() + eps).sqrt().to(var.dtype)


class StackedBatchNorm(nn.Module):
    """Batch normalisation of ``[R, ..., F]`` per member: each member's features are normalised
    by the mean and (biased) variance over its own rows in training mode, by its running
    estimates in evaluation mode (updated in training as ``torch.nn.BatchNorm1d`` does, with
    ``momentum`` and the unbiased variance), then scaled and shifted by its own ``weight`` and
    ``bias`` (``[R, F]``). The standard deviation is taken in float64 and rounded (correctly
    rounded, as ``learners.optim.exact_sqrt``), so it does not depend on the CPU's vector math."""

    def __init__(self, members: int, features: int, momentum: float = 0.01, eps: float = 1e-3):
        super().__init__()
        self.members, self.momentum, self.eps = members, momentum, eps
        self.weight = nn.Parameter(torch.ones(members, features))
        self.bias = nn.Parameter(torch.zeros(members, features))
        self.register_buffer("running_mean", torch.zeros(members, features))
        self.register_buffer("running_var", torch.ones(members, features))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return stacked_batch_norm(x, self.weight, self.bias, self.running_mean, self.running_var, self.training,
                                  self.momentum, self.eps)


def stacked_batch_norm(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, running_mean: torch.Tensor,
                       running_var: torch.Tensor, training: bool, momentum: float, eps: float) -> torch.Tensor:
    """``StackedBatchNorm``'s computation with the given parameters and running estimates (``[M, F]``;
    updated in place in training), for ``x`` ``[M, ..., F]``: M may hold any number of stacked networks."""
    flat = x.reshape(weight.shape[0], -1, x.shape[-1])
    if training:
        mean = flat.mean(1)
        var = (flat - mean.unsqueeze(1)).square().mean(1)
        with torch.no_grad():
            rows = flat.shape[1]
            unbiased = var * (rows / max(rows - 1, 1))
            running_mean.mul_(1 - momentum).add_(momentum * mean)
            running_var.mul_(1 - momentum).add_(momentum * unbiased)
    else:
        mean, var = running_mean, running_var
    std = wide_std(var, eps)
    out = (flat - mean.unsqueeze(1)) / std.unsqueeze(1) * weight.unsqueeze(1) + bias.unsqueeze(1)
    return out.reshape(x.shape)


class StackedBNCriticNet(nn.Module):
    """CrossQ's critic for R members, ``Q(s, a)`` as ``[R, ..., 1]``: batch normalisation of the
    input and after every hidden layer (before its activation), none after the output layer."""

    def __init__(self, members: int, in_features: int, hidden: Sequence[int], activation: str = "relu",
                 momentum: float = 0.01):
        super().__init__()
        sizes = [in_features, *hidden, 1]
        self.layers = nn.ModuleList(StackedLinear(members, a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.norms = nn.ModuleList(StackedBatchNorm(members, width, momentum) for width in sizes[:-1])
        self.activation = _STACKED_ACTIVATIONS[activation]

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        x = inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1)
        x = self.norms[0](x)
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if i + 1 < len(self.layers):
                x = per_member(self.activation, self.norms[i + 1](x))
        return x

    def forward_stacked(self, x: torch.Tensor, parameters: dict[str, torch.Tensor], training: bool) -> torch.Tensor:
        """``forward`` on ``x`` ``[S, N, in]`` with the named parameters and running estimates of S
        stacked networks (``[S, ...]`` each, as ``named_parameters``/``named_buffers`` name them;
        the estimates updated in place in ``training``): what each computes alone, in one pass."""
        norms = self.norms

        def norm(i: int, h: torch.Tensor) -> torch.Tensor:
            return stacked_batch_norm(h, parameters[f"norms.{i}.weight"], parameters[f"norms.{i}.bias"],
                                      parameters[f"norms.{i}.running_mean"], parameters[f"norms.{i}.running_var"],
                                      training, norms[i].momentum, norms[i].eps)

        x = norm(0, x)
        for i in range(len(self.layers)):
            x = stacked_linear(x, parameters[f"layers.{i}.weight"], parameters[f"layers.{i}.bias"])
            if i + 1 < len(self.layers):
                x = per_member(self.activation, norm(i + 1, x))
        return x


class StackedGaussianPolicyNet(nn.Module):
    """``learners.solo.GaussianPolicyNet`` for R members: ``[R, ..., obs] -> (loc, scale)``."""

    def __init__(self, members: int, obs_dim: int, action_dim: int, hidden: Sequence[int], activation: str = "tanh"):
        super().__init__()
        self.body = StackedMLP(members, [obs_dim, *hidden], activation)
        self.loc_head = StackedLinear(members, hidden[-1], action_dim)
        self.scale_head = StackedLinear(members, hidden[-1], action_dim)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        rows, shape = _pad_rows(observation, self.act_rows)
        h = self.body.forward_rows(rows)
        loc = per_member(torch.tanh, self.loc_head(h))
        scale = per_member(nn.functional.softplus, self.scale_head(h))
        return _unpad_rows(loc, shape), _unpad_rows(scale, shape)

    @torch.no_grad()
    def act(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward``'s values without autograd (an acting policy's call, once per environment step):
        with the project's products, the same operations on the same padded rows in fewer calls
        (no module calls, no per-member checks: the row multiple already aligns every member)."""
        return self.act_values(observation)

    def act_values(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``act`` for a caller that has already turned gradients off."""
        plan = self._act_plan()
        if plan is None or observation.dtype != torch.float32 or observation.device.type != "cpu":
            return self(observation)
        layers, activation, rows_multiple, (loc_w, loc_b), (scale_w, scale_b) = plan
        members, features = observation.shape[0], observation.shape[-1]
        rows = observation.reshape(members, -1, features)
        count = rows.shape[1]
        if count % rows_multiple:
            rows = nn.functional.pad(rows, (0, 0, 0, (-count) % rows_multiple))
        h = rows
        for weight, bias in layers:
            h = activation(kernel_ops._forward(h, weight, bias))
        loc = torch.tanh(kernel_ops._forward(h, loc_w, loc_b))
        scale = nn.functional.softplus(kernel_ops._forward(h, scale_w, scale_b))
        if loc.shape[1] != count:
            loc, scale = loc[:, :count], scale[:, :count]
        out = (*observation.shape[:-1], loc.shape[-1])
        return loc.reshape(out), scale.reshape(out)

    def _act_plan(self):
        """What ``act_values`` reads, or None where the project's products do not apply (``numerics``
        other than fma, float64, a GPU). Read through the modules' own dictionaries: the attribute
        lookups of ``nn.Module`` would cost more than the products at one row per member."""
        modules = self._modules
        body = modules["body"]
        layers = [*body._modules["layers"]._modules.values(), modules["loc_head"], modules["scale_head"]]
        pairs = [(layer._parameters["weight"], layer._parameters["bias"]) for layer in layers]
        first = pairs[0][0]
        if not (kernels.active() and first.device.type == "cpu" and first.dtype == torch.float32):
            return None
        rows = math.lcm(body.row_multiple, ALIGN // math.gcd(ALIGN, pairs[-2][0].shape[1]))
        return pairs[:-2], body.activation, rows, pairs[-2], pairs[-1]

    @property
    def act_rows(self) -> int:
        """The row multiple ``forward`` pads to (every member's activations and heads aligned)."""
        return math.lcm(self.body.row_multiple, ALIGN // math.gcd(ALIGN, self.loc_head.weight.shape[1]))


class StackedLayerNorm(nn.Module):
    """Layer normalisation of ``[R, N, F]`` rows per member: each row's features normalised by their
    mean and (biased) variance (``torch.nn.functional.layer_norm``, one pass forward and backward),
    then scaled and shifted by the member's ``weight`` and ``bias`` (``[R, F]``). Each row's
    statistics are its own, computed the same way whatever the other rows, so a member's values do
    not depend on the other members; ATen's kernel takes its one square root per row with the
    correctly rounded ``std::sqrt``, and its vector width is the numerics mode's (fixed at AVX2 in
    ``fma`` and ``portable``)."""

    def __init__(self, members: int, features: int, eps: float = 1e-5):
        super().__init__()
        self.eps = eps
        self.weight = nn.Parameter(torch.ones(members, features))
        self.bias = nn.Parameter(torch.zeros(members, features))

    def reset_parameters(self, generators: Sequence[torch.Generator | None] = ()) -> None:
        """Unit scales and zero shifts (nothing is drawn)."""
        with torch.no_grad():
            self.weight.fill_(1.0)
            self.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return stacked_layer_norm(x, self.weight, self.bias, self.eps)


def stacked_layer_norm(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """``StackedLayerNorm``'s computation with the given parameters (``[S, F]`` for inputs ``[S, N, F]``)."""
    normalised = nn.functional.layer_norm(x, x.shape[-1:], eps=eps)
    return torch.addcmul(bias.unsqueeze(1), normalised, weight.unsqueeze(1))


class StackedDropout(nn.Module):
    """Dropout of ``[R, N, F]`` in training mode: each element kept with probability ``1 - rate`` and
    scaled by ``1 / (1 - rate)``, member r's mask drawn from ``generators[r]`` (``[N, F]`` uniform
    draws per call), so a member's masks do not depend on the other members. As PyTorch's own
    dropout, the input is multiplied by a mask of zeros and ``1 / (1 - rate)`` (one float product
    forward and backward; a boolean mask would cost a mixed-type product, ~30x slower on CPU). The
    identity in evaluation mode."""

    def __init__(self, rate: float, generators: Sequence[torch.Generator]):
        super().__init__()
        self.rate, self.generators = rate, list(generators)

    @property
    def active(self) -> bool:
        return self.training and self.rate != 0

    def mask(self, shape: Sequence[int], like: torch.Tensor) -> torch.Tensor:
        """Each member's mask, ``[R, *shape]`` of ``like``'s dtype: ``1 / (1 - rate)`` where an element
        is kept (its uniform draw at least ``rate``), 0 where it is dropped."""
        draws = torch.stack([torch.rand(tuple(shape), generator=g, device=like.device, dtype=like.dtype)
                             for g in self.generators])
        return (draws >= self.rate).to(like.dtype).mul_(1 / (1 - self.rate))

    @staticmethod
    def apply_mask(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """``x`` times ``mask`` (which broadcasts against it)."""
        return x * mask

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.active:
            return x
        return self.apply_mask(x, self.mask(x.shape[1:], x))


class _RegularisedMLP(StackedMLP):
    """A ``StackedMLP`` whose hidden layers are Linear -> dropout -> layer norm -> activation (DroQ's
    Q-network; either part may be off)."""

    def __init__(self, members: int, sizes: Sequence[int], activation: str, dropout: float, layer_norm: bool,
                 generators: Sequence[torch.Generator] | None):
        super().__init__(members, sizes, activation, linear_output=True)
        if dropout and generators is None:
            raise ValueError("dropout needs the members' generators")
        hidden = sizes[1:-1]
        self.dropouts = nn.ModuleList(StackedDropout(dropout, generators) for _ in hidden) if dropout else None
        self.norms = nn.ModuleList(StackedLayerNorm(members, width) for width in hidden) if layer_norm else None

    def forward_rows(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward_rows_with(x, [(layer.weight, layer.bias) for layer in self.layers])

    def forward_with(self, x: torch.Tensor, parameters: Sequence[tuple[torch.Tensor, torch.Tensor]],
                     norms: Sequence[tuple[torch.Tensor, torch.Tensor]] | None = None, copies: int = 1) -> torch.Tensor:
        """``forward`` with other parameters (see ``forward_rows_with``)."""
        rows, shape = _pad_rows(x, self.row_multiple)
        return _unpad_rows(self.forward_rows_with(rows, parameters, norms, copies), shape)

    def forward_rows_with(self, x: torch.Tensor, parameters: Sequence[tuple[torch.Tensor, torch.Tensor]],
                          norms: Sequence[tuple[torch.Tensor, torch.Tensor]] | None = None,
                          copies: int = 1) -> torch.Tensor:
        """``forward_rows`` of ``copies`` sets of the members' networks in one pass: the parameters'
        leading dimension (and ``x``'s) holds ``copies * R`` networks, set after set (a
        (weight, bias) pair per layer, and per layer norm in ``norms``: the layer norms' current
        parameters when ``None``). Each member's dropout masks are drawn as ``copies`` successive
        calls of ``forward_rows`` would draw them (set 0's for every layer, then set 1's, ...), so
        the pass computes what those calls do, bit for bit."""
        if norms is None and self.norms is not None:
            norms = [(norm.weight, norm.bias) for norm in self.norms]
        masks = None
        if self.dropouts is not None and self.dropouts[0].active:
            drawn = [[dropout.mask(x.shape[1:-1] + (layer[0].shape[-2],), x)
                      for dropout, layer in zip(self.dropouts, parameters)] for _ in range(copies)]
            masks = [torch.cat(per_set) if copies > 1 else per_set[0] for per_set in zip(*drawn)]
        last = len(parameters) - 1
        for i, (weight, bias) in enumerate(parameters):
            x = stacked_linear(x, weight, bias)
            if i < last:
                if masks is not None:
                    x = self.dropouts[i].apply_mask(x, masks[i])
                if norms is not None:
                    x = stacked_layer_norm(x, *norms[i], self.norms[i].eps)
                x = per_member(self.activation, x)
        return x


class StackedCriticNet(nn.Module):
    """``learners.solo.CriticNet`` for R members: V(s) or Q(s, a), ``[R, ..., outputs]`` (one value,
    or TQC's quantiles of the return). With ``dropout`` or ``layer_norm`` (DroQ's Q-networks) each
    hidden layer is Linear -> dropout -> layer norm -> activation, member r's dropout masks drawn
    from ``generators[r]``."""

    def __init__(self, members: int, in_features: int, hidden: Sequence[int], activation: str = "tanh",
                 outputs: int = 1, dropout: float = 0.0, layer_norm: bool = False,
                 generators: Sequence[torch.Generator] | None = None):
        super().__init__()
        sizes = [in_features, *hidden, outputs]
        if dropout or layer_norm:
            self.net = _RegularisedMLP(members, sizes, activation, dropout, layer_norm, generators)
        else:
            self.net = StackedMLP(members, sizes, activation, linear_output=True)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.net(inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1))


class StackedResidualCriticNet(nn.Module):
    """A BRO-style Q-network for R members (Nauman et al., 2024, "BroNet"): ``Q(s, a)`` as
    ``[R, ..., outputs]`` from an embedding Linear -> layer norm -> activation of ``width`` units,
    then ``blocks`` residual blocks x + LN(Linear(act(LN(Linear(x))))), then a linear output.
    Layer normalisation keeps the hidden units' scale fixed, so the network can grow wide and take
    many gradient steps without its values drifting; the residual path keeps it trainable in depth.
    Rows are padded as in ``StackedMLP``, so a member computes what it computes alone."""

    def __init__(self, members: int, in_features: int, width: int, blocks: int, activation: str = "relu",
                 outputs: int = 1):
        super().__init__()
        if blocks < 1:
            raise ValueError(f"a residual critic needs at least one block, got {blocks}")
        self.embed = StackedLinear(members, in_features, width)
        self.layers = nn.ModuleList(StackedLinear(members, width, width) for _ in range(2 * blocks))
        self.norms = nn.ModuleList(StackedLayerNorm(members, width) for _ in range(2 * blocks + 1))
        self.head = StackedLinear(members, width, outputs)
        self.activation = _STACKED_ACTIVATIONS[activation]
        self.row_multiple = ALIGN // math.gcd(ALIGN, width)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        x = inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1)
        # the layers' current tensors (TorchRL's losses swap plain tensors in for the parameters)
        parameters = {f"{name}.{kind}": getattr(layer, kind) for name, layer in self.named_modules()
                      if isinstance(layer, (StackedLinear, StackedLayerNorm)) for kind in ("weight", "bias")}
        return self.forward_named(x, parameters)

    def forward_named(self, x: torch.Tensor, parameters: dict[str, torch.Tensor]) -> torch.Tensor:
        """``forward`` of the concatenated inputs with other parameters, by this module's names,
        whose leading dimension may hold any number of stacked networks (``[S, ...]``, ``x``
        ``[S, ..., in]``): what one network of this shape computes for each, in one pass."""
        eps = self.norms[0].eps
        rows, shape = _pad_rows(x, self.row_multiple)

        def linear(name: str, h: torch.Tensor) -> torch.Tensor:
            return stacked_linear(h, parameters[f"{name}.weight"], parameters[f"{name}.bias"])

        def norm(i: int, h: torch.Tensor) -> torch.Tensor:
            return stacked_layer_norm(h, parameters[f"norms.{i}.weight"], parameters[f"norms.{i}.bias"], eps)

        h = per_member(self.activation, norm(0, linear("embed", rows)))
        for i in range(0, len(self.layers), 2):
            inner = per_member(self.activation, norm(i + 1, linear(f"layers.{i}", h)))
            h = h + norm(i + 2, linear(f"layers.{i + 1}", inner))
        return _unpad_rows(linear("head", h), shape)


class MemberNormal(torch.distributions.Normal):
    """``torch.distributions.Normal`` over a population's ``[R, ...]`` parameters, with the
    logarithms of ``log_prob`` and ``entropy`` computed per member (``losses.functional.per_member``),
    so that a member's values do not depend on the other members."""

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        var = self.scale ** 2
        return -((value - self.loc) ** 2) / (2 * var) - per_member(torch.log, self.scale) - _LOG_SQRT_2PI

    def entropy(self) -> torch.Tensor:
        return 0.5 + _LOG_SQRT_2PI + per_member(torch.log, self.scale)


_LOG_SQRT_2PI = math.log(math.sqrt(2 * math.pi))


class ObservationNorm(nn.Module):
    """Running normalisation of the members' observations (SimBa's, Welford's update): member r's inputs
    become ``(x - mean_r) / sqrt(var_r + eps)`` with the mean and variance of every observation member r
    has acted on so far (``update``, once per environment step; never from the replay memory).

    The statistics are float64 and updated and applied element-wise (IEEE's correctly rounded +, -, x, /,
    sqrt): the same bits on every CPU, and member r's numbers depend on its own observations alone.
    ``forward`` takes ``[R, ..., obs]`` and returns float32, clipped to [-CLIP, CLIP] as Stable-Baselines3's
    ``VecNormalize`` clips: an input that hardly varied in training (a ray that always read its range) does
    not become thousands on another track."""

    EPS = 1e-8  # added to the variance (a constant input becomes 0, not a division by 0)
    CLIP = 10.0

    def __init__(self, members: int, size: int):
        super().__init__()
        self.register_buffer("count", torch.zeros(members, dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(members, size, dtype=torch.float64))
        self.register_buffer("m2", torch.zeros(members, size, dtype=torch.float64))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """One observation per member, ``[R, obs]``."""
        x = x.double()
        self.count += 1
        delta = x - self.mean
        self.mean += delta / self.count.unsqueeze(-1)
        self.m2 += delta * (x - self.mean)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = (self.mean.shape[0], *[1] * (x.dim() - 2), self.mean.shape[1])
        var = self.m2 / self.count.clamp(min=1).unsqueeze(-1)
        scale = (var + self.EPS).sqrt()
        return ((x.double() - self.mean.view(shape)) / scale.view(shape)).clamp(-self.CLIP, self.CLIP).to(x.dtype)


class NormalisedActor(nn.Module):
    """An actor network behind its observations' running normalisation: the policy a run with
    ``algo.td.observation_norm`` saves (``actor.pt``: entries ``norm.*`` and ``net.*``) and evaluates."""

    def __init__(self, norm: ObservationNorm, net: nn.Module):
        super().__init__()
        self.norm, self.net = norm, net

    def forward(self, x: torch.Tensor):
        return self.net(self.norm(x))


def reset_parameters(net: nn.Module, generators: Sequence[torch.Generator | None]) -> nn.Module:
    """Initialise every ``StackedLinear`` of ``net`` in registration order, member by member
    from its own generator (so a member's weights depend on its generator alone), every
    ``StackedLayerNorm`` to unit scale and zero shift, and every layer that declares ``stacked_init``
    (``learners.hyperspherical``'s) by its own ``reset_parameters(generators)``."""
    for layer in net.modules():
        if isinstance(layer, (StackedLinear, StackedLayerNorm)) or getattr(layer, "stacked_init", False):
            layer.reset_parameters(generators)
    return net


def member_state_dict(net: nn.Module, member: int) -> dict[str, torch.Tensor]:
    """Member ``member``'s parameters under the names of the solo network of
    ``learners.solo`` (``StackedGaussianPolicyNet`` -> ``GaussianPolicyNet``, ...), so a
    member's saved weights load into the solo network (``evaluate.py``)."""
    return {name: value[member].detach().cpu().clone() for name, value in net.state_dict().items()}


def load_member_state_dict(net: nn.Module, member: int, state: dict[str, torch.Tensor]) -> None:
    """Write a solo network's ``state_dict`` into member ``member`` of ``net``."""
    own = net.state_dict()
    if set(own) != set(state):
        raise ValueError(f"the weights have entries {sorted(state)}, this network {sorted(own)}")
    with torch.no_grad():
        for name, value in state.items():
            own[name][member].copy_(value.to(own[name].device))


class BlockSampler:
    """What a population's acting policies share: member r's random draws come from
    ``generators[r]``, ``block`` steps (one episode) at a time, so that at episode boundaries
    (where checkpoints are taken) the block is used up and the generators hold the whole state;
    and a pause for callers that only probe the policy's output (TorchRL's ``Collector`` when built)."""

    def __init__(self, net: nn.Module, generators: Sequence[torch.Generator], action_dim: int, block: int):
        self.net, self.generators, self.action_dim, self.block = net, list(generators), action_dim, block
        self._step = block
        self._paused = False

    @property
    def at_block_boundary(self) -> bool:
        return self._step == self.block

    @contextlib.contextmanager
    def paused(self):
        """Within this block, calls return the deterministic action without drawing anything."""
        self._paused = True
        try:
            yield self
        finally:
            self._paused = False


class MemberSampler(BlockSampler):
    """The acting policy of a population: observations ``[R, obs]`` -> actions ``[R, D]``,
    a + sigma * noise clipped to [-1, 1], member r's noise from ``generators[r]``, drawn an
    episode at a time (``BlockSampler``). A collector calls it once per step.
    """

    def __init__(self, net: StackedGaussianPolicyNet, generators: Sequence[torch.Generator], action_dim: int,
                 block: int):
        if len(generators) != net.loc_head.members:
            raise ValueError(f"got {len(generators)} generators for {net.loc_head.members} members")
        super().__init__(net, generators, action_dim, block)
        self._noise: torch.Tensor | None = None

    @torch.no_grad()
    def __call__(self, observation: torch.Tensor) -> torch.Tensor:
        if self._paused:
            return self.net.act_values(observation)[0]
        if self._step == self.block:
            self._noise = torch.stack([torch.randn(self.block, self.action_dim, generator=g, device=g.device)
                                       for g in self.generators])
            self._step = 0
        loc, scale = self.net.act_values(observation)
        noise = self._noise[:, self._step]
        self._step += 1
        return (loc + noise * scale).clamp_(-1.0, 1.0)
