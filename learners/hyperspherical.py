"""Hyperspherical networks for a population (SimbaV2's; Lee et al., 2025), stacked like ``learners.networks``.

Every hidden feature vector lives on the unit sphere, and so does every weight vector of a hidden
layer, so the network's scale cannot drift however long it trains:

- ``StackedHyperLinear``: a linear map without bias whose rows (one per output unit) are unit vectors
  (orthogonal at the start; ``project_`` puts them back on the sphere after every optimiser step);
- ``StackedScaler``: a learned per-feature scale ``s * (init / scale)``, its parameter starting at
  ``scale`` (so Adam's steps on it are of the size ``scale`` sets, whatever the value it stands for);
- ``HyperEmbedder``: the input with a constant ``shift`` appended, normalised to the sphere, then a
  hyper-linear map, a scaler, and normalisation again;
- ``HyperLERPBlock``: ``h <- normalise(h + alpha * (mlp(h) - h))``, a learned interpolation towards an
  inverted-bottleneck MLP's output (``expansion`` times wider inside, ReLU), itself normalised;
- ``HyperActorNet``: embedder, blocks, then two heads (a hyper-linear map, a scaler, a linear map with
  bias) for the Gaussian's mean and its log-std, squashed into ``[LOG_STD_MIN, LOG_STD_MAX]`` by tanh;
- ``HyperCriticNet``: the same trunk over (observation, action), its head the logits of a categorical
  distribution over a fixed support of returns (``losses.simbav2``).

Each member's weights are drawn from its own generator (``reset_parameters``), so a member equals its
solo run. Products go through ``learners.networks.stacked_linear`` (the project's ``fma`` kernels where
that numerics mode is on); a vector's length is a sum of squares per row and a square root taken in
float64 (correctly rounded), so rows do not depend on each other or on the CPU's vector math.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

from learners.networks import stacked_linear

EPS = 1e-8  # the smallest length a vector is divided by
LOG_STD_MIN, LOG_STD_MAX = -10.0, 2.0  # the actor's log-std range


def l2normalise(x: torch.Tensor, eps: float = EPS) -> torch.Tensor:
    """``x / max(|x|, eps)`` along the last dimension."""
    length = x.square().sum(-1, keepdim=True).double().sqrt().to(x.dtype)
    return x / length.clamp_min(eps)


class StackedHyperLinear(nn.Module):
    """R bias-free linear maps ``[R, ..., in] -> [R, ..., out]`` whose weight rows are unit vectors."""

    stacked_init = True  # learners.networks.reset_parameters draws its weights

    def __init__(self, members: int, in_features: int, out_features: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(members, out_features, in_features))

    def reset_parameters(self, generators: Sequence[torch.Generator | None]) -> None:
        """Orthogonal rows (member r's from ``generators[r]``), each of unit length."""
        with torch.no_grad():
            for weight, generator in zip(self.weight, generators):
                nn.init.orthogonal_(weight, generator=generator)
            self.project_()

    @torch.no_grad()
    def project_(self) -> None:
        """Every row back onto the unit sphere (after an optimiser step)."""
        self.weight.copy_(l2normalise(self.weight))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return stacked_linear(x, self.weight, self.weight.new_zeros(self.weight.shape[:2]))


class StackedScaler(nn.Module):
    """A learned per-feature scale for each member: ``x * s * (init / scale)``, ``s`` starting at ``scale``."""

    stacked_init = True

    def __init__(self, members: int, features: int, init: float, scale: float):
        super().__init__()
        self.init, self.scale = float(init), float(scale)
        self.weight = nn.Parameter(torch.full((members, features), self.scale))

    def reset_parameters(self, generators: Sequence[torch.Generator | None] = ()) -> None:
        with torch.no_grad():
            self.weight.fill_(self.scale)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = (self.weight.shape[0], *[1] * (x.dim() - 2), self.weight.shape[1])
        return x * (self.weight * (self.init / self.scale)).view(shape)


class StackedBias(nn.Module):
    """A learned bias per member, zero at the start (the heads' outputs)."""

    stacked_init = True

    def __init__(self, members: int, features: int):
        super().__init__()
        self.weight = nn.Parameter(torch.zeros(members, features))

    def reset_parameters(self, generators: Sequence[torch.Generator | None] = ()) -> None:
        with torch.no_grad():
            self.weight.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = (self.weight.shape[0], *[1] * (x.dim() - 2), self.weight.shape[1])
        return x + self.weight.view(shape)


class HyperEmbedder(nn.Module):
    def __init__(self, members: int, in_features: int, width: int, shift: float):
        super().__init__()
        self.shift = float(shift)
        self.linear = StackedHyperLinear(members, in_features + 1, width)
        self.scaler = StackedScaler(members, width, math.sqrt(2 / width), math.sqrt(2 / width))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = l2normalise(torch.cat([x, torch.full_like(x[..., :1], self.shift)], -1))
        return l2normalise(self.scaler(self.linear(x)))


class HyperLERPBlock(nn.Module):
    def __init__(self, members: int, width: int, blocks: int, expansion: int = 4):
        super().__init__()
        inner, scale = width * expansion, math.sqrt(2 / width) / math.sqrt(expansion)
        self.up = StackedHyperLinear(members, width, inner)
        self.scaler = StackedScaler(members, inner, scale, scale)
        self.down = StackedHyperLinear(members, inner, width)
        self.alpha = StackedScaler(members, width, 1 / (blocks + 1), 1 / math.sqrt(width))

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        update = l2normalise(self.down(torch.relu(self.scaler(self.up(h))) + EPS))
        return l2normalise(h + self.alpha(update - h))


class HyperTrunk(nn.Module):
    """Embedder and ``blocks`` LERP blocks: ``[R, ..., in] -> [R, ..., width]`` on the unit sphere."""

    def __init__(self, members: int, in_features: int, width: int, blocks: int, shift: float):
        super().__init__()
        self.embed = HyperEmbedder(members, in_features, width, shift)
        self.blocks = nn.ModuleList(HyperLERPBlock(members, width, blocks) for _ in range(blocks))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.embed(x)
        for block in self.blocks:
            h = block(h)
        return h


class HyperHead(nn.Module):
    """A hyper-linear map and a unit scaler, then a plain (unit-row) map to ``outputs`` with a bias."""

    def __init__(self, members: int, width: int, outputs: int):
        super().__init__()
        self.hidden = StackedHyperLinear(members, width, width)
        self.scaler = StackedScaler(members, width, 1.0, 1.0)
        self.out = StackedHyperLinear(members, width, outputs)
        self.bias = StackedBias(members, outputs)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        return self.bias(self.out(self.scaler(self.hidden(h))))


class HyperActorNet(nn.Module):
    """``[R, ..., obs] -> (loc, scale)`` of the tanh-squashed Gaussian the off-policy learners sample."""

    def __init__(self, members: int, obs_dim: int, action_dim: int, width: int, blocks: int = 1, shift: float = 3.0):
        super().__init__()
        self.trunk = HyperTrunk(members, obs_dim, width, blocks, shift)
        self.mean = HyperHead(members, width, action_dim)
        self.log_std = HyperHead(members, width, action_dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.trunk(x)
        log_std = LOG_STD_MIN + (LOG_STD_MAX - LOG_STD_MIN) * 0.5 * (1 + torch.tanh(self.log_std(h)))
        return self.mean(h), log_std.exp()


class HyperCriticNet(nn.Module):
    """``[R, ..., obs + action] -> [R, ..., bins]``: the logits of the return's categorical distribution."""

    def __init__(self, members: int, in_features: int, bins: int, width: int, blocks: int = 1, shift: float = 3.0):
        super().__init__()
        self.trunk = HyperTrunk(members, in_features, width, blocks, shift)
        self.head = HyperHead(members, width, bins)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        """The inputs (observation, then action) are read concatenated."""
        return self.head(self.trunk(inputs[0] if len(inputs) == 1 else torch.cat(inputs, -1)))


def hyper_weights(net: nn.Module, params=None) -> list[torch.Tensor]:
    """The weights of every ``StackedHyperLinear`` of ``net``: its own parameters, or the entries of the same
    names in ``params`` (a loss's functional copy of ``net``'s parameters, a TensorDict whose names may carry a
    prefix such as TorchRL's ``module.``), to put back on the sphere after each optimiser step (``project``)."""
    names = [f"{name}.weight" if name else "weight" for name, layer in net.named_modules()
             if isinstance(layer, StackedHyperLinear)]
    if params is None:
        own = dict(net.named_parameters())
        return [own[name] for name in names]
    flat = params.flatten_keys(".")
    return [value for key, value in flat.items() if any(key == n or key.endswith("." + n) for n in names)]


@torch.no_grad()
def project(weights: Sequence[torch.Tensor]) -> None:
    """Every row of every weight back onto the unit sphere (in place)."""
    for weight in weights:
        weight.copy_(l2normalise(weight))
