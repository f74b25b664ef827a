"""The paper's update steps on plain tensors, their backward passes written out (``FusedSteps``).

A Monte-Carlo critic step is small: three products forward, five backward, two activations and
Adam, on minibatches of 100-200 transitions. Through the loss module it also pays for TensorDict
minibatches, the loss's TensorDict output, autograd's graph and engine, and a Python call per
layer and per padding: about as much again as the products at R = 1. Here the same operations
run in the same order on the same tensors, with each gradient computed as autograd computes it
(the same kernels and ATen functions, the same formulas), so a step gives the loss module's
numbers bit for bit (``tests/test_fused_phases.py`` holds them to it, step by step and over whole
runs) at less than half its per-step overhead.

What it covers: the critic step of SPG's and PPO's phases (uniform minibatches; prioritised replay
takes the loss module's path), with the project's products (``numerics=fma``: the products are
``learners.kernels``'s, whose backward this module calls directly), on the CPU, in float32, with the
paper's tanh activation. Anything else (other activations, ``numerics`` native or portable, a GPU,
``compile=true``) takes the loss module's path, which stays the reference.
"""

from __future__ import annotations

import torch

from learners import kernels
from learners.kernels import ops as kernel_ops
from learners.networks import StackedCriticNet, StackedMLP, fast_tanh


def critic_available(critic_net: torch.nn.Module) -> bool:
    """Whether ``FusedCritic`` computes this critic's step (else the loss module's path)."""
    mlp = getattr(critic_net, "net", None)
    if type(critic_net) is not StackedCriticNet or type(mlp) is not StackedMLP:
        return False
    params = list(critic_net.parameters())
    return (kernels.active() and mlp.activation is fast_tanh and mlp.linear_output
            and all(p.device.type == "cpu" and p.dtype == torch.float32 for p in params))


def _tanh(x: torch.Tensor) -> torch.Tensor:
    """``learners.networks.fast_tanh``'s forward values (its eager autograd function's arithmetic)."""
    return torch.sigmoid(x * 2.0).mul_(2.0).sub_(1.0)


class FusedCritic:
    """One Monte-Carlo critic step, mean (G - critic)^2 per member, minimised with its optimiser.

    ``step(inputs, target)`` computes what ``PhaseLoss.critic_loss`` then ``objective``, backward and
    ``MemberAdam.step`` compute, bit for bit: the forward of ``StackedMLP`` (rows padded to its row
    multiple, the kernels' products, ``fast_tanh``), the loss, and the gradients autograd would
    take (the mean's division, the square's ``2 d``, the kernels' input and weight gradients and
    column sums, ``tanh_backward``), then Adam on them.
    """

    def __init__(self, critic_net: StackedCriticNet, optimiser, active: torch.Tensor):
        if not critic_available(critic_net):
            raise ValueError("FusedCritic needs a tanh StackedCriticNet in float32 on the CPU with numerics=fma")
        self.mlp: StackedMLP = critic_net.net
        self.layers = [(layer.weight, layer.bias) for layer in self.mlp.layers]
        self.optimiser = optimiser
        self.active = active
        self._params = [p for pair in self.layers for p in pair]
        if [id(p) for p in optimiser.params] != [id(p) for p in self._params]:
            raise ValueError("the critic's optimiser must hold the critic's parameters in layer order")

    def step(self, inputs: torch.Tensor, target: torch.Tensor) -> dict[str, torch.Tensor]:
        """One Adam step on the minibatch ``inputs`` ``[R, B, in]`` with returns ``target`` ``[R, B, 1]``;
        returns the step's diagnostics (``loss_critic``, ``value_mean``: one value per member)."""
        with torch.no_grad():
            members, batch = inputs.shape[0], inputs.shape[1]
            rows = batch + (-batch) % self.mlp.row_multiple
            x = inputs if rows == batch else torch.nn.functional.pad(inputs, (0, 0, 0, rows - batch))
            # forward, keeping each layer's input
            seen = [x]
            last = len(self.layers) - 1
            for i, (weight, bias) in enumerate(self.layers):
                x = kernel_ops._forward(x, weight, bias)
                if i < last:
                    x = _tanh(x)
                    seen.append(x)
            value = x[:, :batch] if rows != batch else x
            error = target - value
            loss = error.pow(2).reshape(members, -1).mean(-1)
            value_mean = value.reshape(members, -1).mean(-1)
            # backward: d/d value of sum_r active_r * mean((G - value)^2)
            count = error[0].numel()
            grad = self.active.unsqueeze(-1).expand(members, count) / count
            grad = -(grad.reshape(error.shape) * (error.pow(1.0) * 2.0))
            if rows != batch:
                grad = torch.nn.functional.pad(grad, (0, 0, 0, rows - batch))
            grads = [None] * len(self._params)
            for i in range(last, -1, -1):
                weight, _ = self.layers[i]
                h = seen[i]
                grads[2 * i] = kernel_ops._weight_grad(grad, h)
                grads[2 * i + 1] = kernel_ops.colsum(grad)
                if i > 0:
                    grad = torch.ops.aten.tanh_backward(kernel_ops._input_grad(grad, weight), h)
            for p, g in zip(self._params, grads):
                p.grad = g
        self.optimiser.step()
        return {"loss_critic": loss, "value_mean": value_mean}

