"""What the losses share: the two-phase loss base class, and cheap module calls.

``PhaseLoss`` holds what SPG and PPO have in common: the Monte-Carlo critic loss, the
entropy term, ``forward`` and no-op phase hooks.

Calling TorchRL modules from inside a loss, cheaply:

A loss calls its networks dozens of times per training step on small batches, where the
TensorDict bookkeeping of a module call (writing outputs into a TensorDict, then reading them
back) costs as much as the arithmetic. For the common structures (a plain ``TensorDictModule``;
a probabilistic actor made of one ``TensorDictModule`` and its distribution head) these helpers
call the wrapped ``nn.Module`` on the input tensors directly. Any other structure takes the
general TensorDict path; the results are the same (``tests/test_losses.py`` checks it).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential, TensorDictModule
from torchrl.objectives import LossModule

from losses import functional as F

PRIORITY_WEIGHT_KEY = "priority_weight"  # importance weights of a prioritised minibatch (TorchRL's key)
PRIORITY_KEY = "td_error"  # where a loss leaves per-transition errors for the sampler's priorities


def value_function(module: TensorDictModule) -> Callable[[TensorDictBase], torch.Tensor]:
    """``td -> module's single output``, not written into ``td``."""
    if len(module.out_keys) != 1:
        raise ValueError(f"a critic must have one output key, got {module.out_keys}")
    out_key = module.out_keys[0]
    if type(module) is TensorDictModule:
        net, in_keys = module.module, list(module.in_keys)
        return lambda td: net(*(td.get(key) for key in in_keys))
    return lambda td: module(td.copy()).get(out_key)


def module_call(module, x: torch.Tensor, params: TensorDictBase | None = None):
    """``module``'s network (a ``TensorDictModule``'s inner ``nn.Module``, else the module) on the tensor
    ``x``, with ``params`` (e.g. a loss's target parameters) swapped in for the call when given."""
    net = getattr(module, "module", module)
    if params is None:
        return net(x)
    with params.to_module(module):
        return net(x)


def distribution_function(actor: ProbabilisticTensorDictSequential) -> Callable[[TensorDictBase],
                                                                                torch.distributions.Distribution]:
    """``td -> actor.get_dist(td)``."""
    parts = list(getattr(actor, "module", []))
    if (len(parts) == 2 and type(parts[0]) is TensorDictModule
            and isinstance(parts[1], ProbabilisticTensorDictModule)
            and list(parts[0].out_keys) == list(parts[1].in_keys)):
        params_module, head = parts
        net, in_keys = params_module.module, list(params_module.in_keys)
        names = [key[-1] if isinstance(key, tuple) else key for key in head.dist_keys]
        make, kwargs = head.distribution_class, dict(head.distribution_kwargs)

        def fast(td: TensorDictBase) -> torch.distributions.Distribution:
            params = net(*(td.get(key) for key in in_keys))
            params = params if isinstance(params, tuple) else (params,)
            return make(**dict(zip(names, params)), **kwargs)

        return fast
    return lambda td: actor.get_dist(td.copy())


def cached(owner, module, make: Callable) -> Callable:
    """``make(module)``, built once per (owner, module) and kept on ``owner``."""
    cache = owner.__dict__.setdefault("_call_cache", {})
    key = (id(module), make)
    function = cache.get(key)
    if function is None:
        function = cache[key] = make(module)
    return function


class PhaseLoss(LossModule):
    """Base of the paper's losses, optimised in a critic phase then an actor phase.

    Subclasses set ``critic_attr`` (the attribute holding the critic module), ``entropy_coeff``
    and ``joint_log_prob``, define ``actor_loss`` and override the hooks they need.

    Populations: with ``members=R`` the networks are a population's stacked networks
    (``learners.networks``), every tensor has the members on its first dimension
    (``[R, B, ...]``), and every loss and diagnostic is one value per member, shape ``[R]``
    (sum the losses over members before ``backward``: each member's gradient is then its
    own). With ``members=None`` (the default) they are scalars, as TorchRL's losses.
    """

    critic_attr: str
    critic_metrics = ("loss_critic", "value_mean")
    members: int | None = None

    def _mean(self, values: torch.Tensor) -> torch.Tensor:
        """A scalar, or one mean per member in a population."""
        return F.mean(values, self.members is not None)

    def draw(self, tensordict: TensorDictBase) -> None:
        """Add to an actor step's minibatch the random draws its loss needs (none here), before
        ``actor_loss``: a compiled loss cannot call the members' generators."""

    def before_critic_phase(self, data: TensorDictBase) -> None:
        """Called once with the phase's whole data before its critic steps."""

    def before_actor_phase(self, data: TensorDictBase) -> None:
        """Called once with the phase's whole data before its actor steps."""

    def after_actor_phase(self) -> None:
        """Called once after the phase's actor steps."""

    def critic_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Mean (G - critic)^2 with G the Monte-Carlo return.

        With importance weights in ``tensordict`` (``"priority_weight"``, prioritised replay) the
        mean is weighted, and the output also holds each transition's |G - critic| under
        ``"td_error"`` (the sampler's new priorities; not a loss term)."""
        value = self._value(tensordict)
        target = tensordict[self.tensor_keys.value_target]
        weight = tensordict.get(PRIORITY_WEIGHT_KEY, None)
        if weight is None:
            loss = F.squared_error(value, target, self.members is not None)
            return TensorDict({"loss_critic": loss, "value_mean": self._mean(value.detach())})
        error = target - value
        loss = self._mean(weight.reshape(error.shape) * error.pow(2))
        return TensorDict({"loss_critic": loss, "value_mean": self._mean(value.detach()),
                           PRIORITY_KEY: error.detach().abs().reshape(weight.shape)})

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Actor and critic terms on one batch (the ``loss_*`` entries sum to the total loss)."""
        return self.actor_loss(tensordict).update(self.critic_loss(tensordict))

    def _entropy(self, dist: torch.distributions.Distribution) -> tuple[torch.Tensor, torch.Tensor]:
        """(mean entropy, detached; the loss term -coeff * entropy, with no gradient if coeff is 0)."""
        entropy = self._mean(F.per_dimension_or_joint(dist.entropy(), self.joint_log_prob))
        term = -self.entropy_coeff * (entropy if self.entropy_coeff else entropy.detach())
        return entropy.detach(), term

    def bind_calls(self) -> None:
        """Build the cheap network calls now rather than at first use (a compiled step guards on
        them, and would compile again when the other phase adds its own)."""
        self._policy_call()
        self._value_call()

    def _policy_call(self) -> Callable[[TensorDictBase], torch.distributions.Distribution]:
        return cached(self, self.actor_network, distribution_function)

    def _value_call(self) -> Callable[[TensorDictBase], torch.Tensor]:
        return cached(self, getattr(self, self.critic_attr), value_function)

    def _policy(self, tensordict: TensorDictBase) -> torch.distributions.Distribution:
        return self._policy_call()(tensordict)

    def _value(self, tensordict: TensorDictBase) -> torch.Tensor:
        return self._value_call()(tensordict)


def _members(members: int | None) -> int | None:
    if members is not None and (isinstance(members, bool) or not isinstance(members, int) or members < 1):
        raise ValueError(f"members must be None (no population) or an integer >= 1, got {members!r}")
    return members
