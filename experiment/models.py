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



class Tanh(nn.Module):
    """tanh(x); on large inputs computed as 2 * sigmoid(2x) - 1.

    The same function to within 2.4e-7 (absolute), and about 3.7x faster than ``torch.tanh``
    on minibatch-sized inputs on CPU builds whose float32 tanh is not vectorised (this one's;
    ``benchmarks/train_speed.py`` measures it). Small inputs (acting, one state at a time) take
    ``torch.tanh``: one call is cheaper than three there.
    """

    SMALL = 4096

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.numel() <= self.SMALL:
            return torch.tanh(x)
        return torch.sigmoid(2.0 * x).mul(2.0).sub(1.0)


ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": Tanh, "relu": nn.ReLU, "elu": nn.ELU}


def mlp(in_features: int, hidden: Sequence[int], activation: str) -> tuple[nn.Sequential, int]:
    """Hidden layers only; returns the stack and its output width."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_features, width), ACTIVATIONS[activation]()]
        in_features = width
    return nn.Sequential(*layers), in_features


def glorot_(module: nn.Module) -> nn.Module:
    """Glorot-uniform kernels and zero biases for every linear layer of ``module``."""
    for layer in module.modules():
        if isinstance(layer, nn.Linear):
            nn.init.xavier_uniform_(layer.weight)
            nn.init.zeros_(layer.bias)
    return module


class GaussianPolicyNet(nn.Module):
    """observation -> (loc, scale) of a diagonal Normal; loc in (-1, 1), scale > 0."""

    def __init__(self, obs_dim: int, action_dim: int, hidden: Sequence[int], activation: str = "tanh"):
        super().__init__()
        self.body, width = mlp(obs_dim, hidden, activation)
        self.loc_head = nn.Linear(width, action_dim)
        self.scale_head = nn.Linear(width, action_dim)
        glorot_(self)

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.body(observation)
        return torch.tanh(self.loc_head(h)), nn.functional.softplus(self.scale_head(h))


class CriticNet(nn.Module):
    """Its inputs concatenated -> one value: V(s) with one input, Q(s, a) with two."""

    def __init__(self, in_features: int, hidden: Sequence[int], activation: str = "tanh"):
        super().__init__()
        body, width = mlp(in_features, hidden, activation)
        self.net = glorot_(nn.Sequential(*body, nn.Linear(width, 1)))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor:
        return self.net(inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1))


def make_actor(net: GaussianPolicyNet) -> ProbabilisticActor:
    """The stochastic policy as a TorchRL actor: ``observation`` -> ``loc``, ``scale``, ``action``.

    The distribution is ``torch.distributions.Normal``, so log-probabilities are per action
    dimension. Sampling (in RANDOM exploration mode) does not clip: see ``make_policy``.
    """
    return ProbabilisticActor(
        TensorDictModule(net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], out_keys=["action"],
        distribution_class=torch.distributions.Normal,
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
