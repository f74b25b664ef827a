"""The paper's networks and their TorchRL wrappings.

Actor: hidden tanh layers, then two heads, mu = tanh(linear) and sigma = softplus(linear),
of a diagonal Normal. Critic: hidden tanh layers and a linear output, V(s) or Q(s, a).
Kernels are Glorot-uniform and biases zero.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torch import nn
from torchrl.modules import ProbabilisticActor



_SMALL = 12_000  # elements; below this one torch.tanh call is cheaper than three


def tanh(x: torch.Tensor, members: int = 1) -> torch.Tensor:
    """tanh(x); on minibatch-sized inputs computed as 2 * sigmoid(2x) - 1.

    The same function to within 2.4e-7 (absolute), and about 2.4x faster than ``torch.tanh``
    on minibatch-sized float32 inputs on CPU builds whose tanh is not vectorised (this one's;
    ``speed/train_speed.py`` measures it). Small inputs (acting, one state at a time) take
    ``torch.tanh``: one call is cheaper than three there. For the stacked networks of a
    population (``members`` on the first dimension) the size that decides is one member's,
    so that a member computes exactly what it computes alone.
    """
    if x.numel() <= _SMALL * members:
        return torch.tanh(x)
    return torch.sigmoid(2.0 * x).mul(2.0).sub(1.0)


ACTIVATIONS: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {
    "tanh": tanh, "relu": torch.relu, "elu": nn.functional.elu}


def glorot_(module: nn.Module) -> nn.Module:
    """Glorot-uniform kernels and zero biases for every linear layer of ``module``."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return module


class MLP(nn.Module):
    """Linear layers, each followed by ``activation`` except (``linear_output``) the last.

    The forward pass applies ``torch.nn.functional.linear`` to each layer's parameters rather
    than calling the layers as modules: the same arithmetic without per-module call overhead,
    which is much of the cost of acting on one state at a time.
    """

    def __init__(self, sizes: Sequence[int], activation: str = "tanh", linear_output: bool = False):
        super().__init__()
        self.layers = glorot_(nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:])))
        self.activation = ACTIVATIONS[activation]
        self.linear_output = linear_output

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x = nn.functional.linear(x, layer.weight, layer.bias)
            if not (self.linear_output and i == last):
                x = self.activation(x)
        return x


class GaussianPolicyNet(nn.Module):
    """observation -> (loc, scale) of a diagonal Normal; loc in (-1, 1), scale > 0."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: Sequence[int], activation: str = "tanh"):
        super().__init__()
        self.body = MLP([obs_dim, *hidden], activation)
        self.loc_head = glorot_(nn.Linear(hidden[-1], action_dim))
        self.scale_head = glorot_(nn.Linear(hidden[-1], action_dim))

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.body(observation)
        loc = torch.tanh(nn.functional.linear(h, self.loc_head.weight, self.loc_head.bias))
        scale = nn.functional.softplus(nn.functional.linear(h, self.scale_head.weight, self.scale_head.bias))
        return loc, scale


class CriticNet(nn.Module):
    """Its inputs concatenated -> one value: V(s) with one input, Q(s, a) with two."""

    def __init__(self, in_features: int, hidden: Sequence[int], activation: str = "tanh"):
        super().__init__()
        self.net = MLP([in_features, *hidden, 1], activation, linear_output=True)

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.net(inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1))


def make_actor(net: nn.Module, distribution: type = torch.distributions.Normal) -> ProbabilisticActor:
    """The stochastic policy as a TorchRL actor: ``observation`` -> ``loc``, ``scale``, ``action``.

    The distribution is ``torch.distributions.Normal`` (or, for a population's stacked networks,
    ``learners.networks.MemberNormal``), so log-probabilities are per action dimension.
    Sampling (in RANDOM exploration mode) does not clip: see ``make_policy``.
    """
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], out_keys=["action"],
        distribution_class=distribution,
        distribution_kwargs={"validate_args": False},  # NaNs are caught by the training loop
    )


def make_policy(actor: ProbabilisticActor) -> TensorDictSequential:
    """The acting policy: sample, then clip to [-1, 1] (the clipped action is stored)."""
    clip = TensorDictModule(lambda action: action.clamp(-1.0, 1.0), in_keys=["action"], out_keys=["action"])
    return TensorDictSequential(actor, clip)


def make_sampler(net: GaussianPolicyNet) -> Callable[[torch.Tensor], torch.Tensor]:
    """``observation -> clipped sampled action`` without TensorDicts, drawing exactly what
    ``make_policy(make_actor(net))`` draws in RANDOM exploration mode (same generator calls)."""

    @torch.no_grad()
    def sample(observation: torch.Tensor) -> torch.Tensor:
        loc, scale = net(observation)
        noise = torch.empty_like(loc).normal_()  # what Normal(loc, scale).rsample() draws
        return (loc + noise * scale).clamp_(-1.0, 1.0)

    return sample


def make_critic(net: CriticNet, state_action: bool) -> TensorDictModule:
    """Q(s, a) -> ``state_action_value`` if ``state_action`` else V(s) -> ``state_value``."""
    if state_action:
        return TensorDictModule(net, in_keys=["observation", "action"], out_keys=["state_action_value"])
    return TensorDictModule(net, in_keys=["observation"], out_keys=["state_value"])
