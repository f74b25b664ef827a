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
(forward, gradients, Adam steps; ``tests/test_stacked.py``). A member's saved weights load
into the solo networks of ``experiment.models`` and compute the same function to float
rounding (``F.linear`` and ``bmm`` accumulate in other orders), so training compares a
population with populations of one, and the solo networks serve evaluation.

Initialisation draws each member's Glorot-uniform kernels from that member's own
``torch.Generator``, in layer order (actor body, heads, then critic when both are built from
the same generator), so a member's initial weights depend on its seed alone.

"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from experiment.models import ACTIVATIONS, tanh


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
        if x.shape[0] != self.members:
            raise ValueError(f"input has {x.shape[0]} members on its first dimension, this layer {self.members}")
        flat = x.reshape(self.members, -1, x.shape[-1])
        if self.weight.shape[1] == 1:
            # A one-unit layer as w x^T: x w^T takes a matrix-vector path whose rounding
            # depends on the number of members; this form's does not.
            out = torch.baddbmm(self.bias.unsqueeze(-1), self.weight, flat.transpose(1, 2)).transpose(1, 2)
        else:
            out = torch.baddbmm(self.bias.unsqueeze(1), flat, self.weight.transpose(1, 2))
        return out.reshape(*x.shape[:-1], out.shape[-1])


class StackedMLP(nn.Module):
    """``experiment.models.MLP`` for R members."""

    def __init__(self, members: int, sizes: Sequence[int], activation: str = "tanh", linear_output: bool = False):
        super().__init__()
        self.layers = nn.ModuleList(StackedLinear(members, a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        self.activation = ACTIVATIONS[activation]
        self.members = members
        self.linear_output = linear_output

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = layer(x)
            if not (self.linear_output and i == last):
                # tanh picks its formula by one member's input size (see experiment.models.tanh)
                x = tanh(x, self.members) if self.activation is tanh else self.activation(x)
        return x


class StackedGaussianPolicyNet(nn.Module):
    """``experiment.models.GaussianPolicyNet`` for R members: ``[R, ..., obs] -> (loc, scale)``."""

    def __init__(self, members: int, obs_dim: int, action_dim: int, hidden: Sequence[int], activation: str = "tanh"):
        super().__init__()
        self.body = StackedMLP(members, [obs_dim, *hidden], activation)
        self.loc_head = StackedLinear(members, hidden[-1], action_dim)
        self.scale_head = StackedLinear(members, hidden[-1], action_dim)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.body(observation)
        return torch.tanh(self.loc_head(h)), nn.functional.softplus(self.scale_head(h))


class StackedCriticNet(nn.Module):
    """``experiment.models.CriticNet`` for R members: V(s) or Q(s, a), ``[R, ..., 1]``."""

    def __init__(self, members: int, in_features: int, hidden: Sequence[int], activation: str = "tanh"):
        super().__init__()
        self.net = StackedMLP(members, [in_features, *hidden, 1], activation, linear_output=True)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.net(inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1))


def reset_parameters(net: nn.Module, generators: Sequence[torch.Generator | None]) -> nn.Module:
    """Initialise every ``StackedLinear`` of ``net`` in registration order, member by member
    from its own generator (so a member's weights depend on its generator alone)."""
    for layer in net.modules():
        if isinstance(layer, StackedLinear):
            layer.reset_parameters(generators)
    return net


def member_state_dict(net: nn.Module, member: int) -> dict[str, torch.Tensor]:
    """Member ``member``'s parameters under the names of the solo network of
    ``experiment.models`` (``StackedGaussianPolicyNet`` -> ``GaussianPolicyNet``, ...), so a
    member's saved weights load into the solo network (``evaluate.py``)."""
    return {name: value[member].detach().clone() for name, value in net.state_dict().items()}


def load_member_state_dict(net: nn.Module, member: int, state: dict[str, torch.Tensor]) -> None:
    """Write a solo network's ``state_dict`` into member ``member`` of ``net``."""
    own = net.state_dict()
    if set(own) != set(state):
        raise ValueError(f"the weights have entries {sorted(state)}, this network {sorted(own)}")
    with torch.no_grad():
        for name, value in state.items():
            own[name][member].copy_(value)
