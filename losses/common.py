"""Calling TorchRL modules from inside a loss, cheaply.

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
from tensordict import TensorDictBase
from tensordict.nn import ProbabilisticTensorDictModule, ProbabilisticTensorDictSequential, TensorDictModule


def value_function(module: TensorDictModule) -> Callable[[TensorDictBase], torch.Tensor]:
    """``td -> module's single output``, not written into ``td``."""
    if len(module.out_keys) != 1:
        raise ValueError(f"a critic must have one output key, got {module.out_keys}")
    out_key = module.out_keys[0]
    if type(module) is TensorDictModule:
        net, in_keys = module.module, list(module.in_keys)
        return lambda td: net(*(td.get(key) for key in in_keys))
    return lambda td: module(td.copy()).get(out_key)


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
