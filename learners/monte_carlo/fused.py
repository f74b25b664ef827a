"""The paper's update steps on plain tensors, their backward passes written out.

A step of SPG's or PPO's phases is small: a few products forward and backward, two activations and
Adam, on minibatches of 100-200 transitions. Through the loss module it also pays for TensorDict
minibatches, the loss's TensorDict output, autograd's graph and engine, and a Python call per
layer and per padding: about as much again as the products. Here the same operations run in the
same order on the same tensors, with each gradient computed as autograd computes it (the same
kernels and ATen functions, the same formulas, the same order of sums where a tensor takes
several gradients), so every step gives the loss module's numbers bit for bit
(``tests/test_fused_phases.py`` holds them to it over whole phases, and the golden runs over whole
runs).

- ``FusedCritic``: the Monte-Carlo critic's step (SPG's Q(s, a), PPO's V(s)).
- ``FusedSPGActor``: SPG's actor step (SPG-p's weights, either centre and baseline), without an
  entropy bonus (the paper's; with one, the loss module's path).
- ``FusedPPOActor``: PPO's actor step, the ratio in linear or log space, with its entropy bonus.

They run with the project's products (``numerics=fma``: the products are ``learners.kernels``'s,
whose backward this module calls directly), on the CPU, in float32, with the paper's tanh
activation, on uniform minibatches. Anything else (prioritised replay, other activations,
``numerics`` native or portable, a GPU, ``compile=true``) takes the loss module's path, which stays
the reference (``learners.monte_carlo.learner.FUSED = False`` forces it). So does a loss the fused
steps do not know (``loss_refusal``): another setting, parameter or submodule, a subclass, or an edit
to any code they copy (``learners.fast_paths``, the one guard of every fast path), so a change to a
loss module is never silently left out: the run says so in one line, naming the function, and
summary.json's ``paths`` records which path ran and why.
"""

from __future__ import annotations

import torch

from learners import fast_paths, kernels
from learners.kernels import ops as kernel_ops
from learners.networks import (_LOG_SQRT_2PI, MemberNormal, StackedCriticNet, StackedGaussianPolicyNet, StackedMLP,
                               fast_tanh)
from losses import functional as F
from losses.spg import _repeat

# The settings each loss module has, as the fused steps know them: a loss with another setting (an
# option added to the loss module and not here), parameter or submodule, or of a subclass, takes
# the loss module's path.
KNOWN_SETTINGS = {
    "SPGLoss": {"baseline", "entropy_coeff", "generators", "joint_log_prob", "members", "num_samples", "prioritised",
                "sample_around", "temperature_decay"},
    "LogClipPPOLoss": {"clip_epsilon", "entropy_coeff", "joint_log_prob", "members", "ratio_space"},
}
KNOWN_MODULES = {"SPGLoss": {"actor_network", "qvalue_network"}, "LogClipPPOLoss": {"actor_network", "critic_network"}}
# What torch's Module, TorchRL's LossModule and losses.common.cached keep on a loss instance.
KNOWN_INTERNALS = {
    "_backward_hooks", "_backward_pre_hooks", "_buffers", "_forward_hooks", "_forward_hooks_always_called",
    "_forward_hooks_with_kwargs", "_forward_pre_hooks", "_forward_pre_hooks_with_kwargs", "_has_update_associated",
    "_is_full_backward_hook", "_load_state_dict_post_hooks", "_load_state_dict_pre_hooks", "_modules",
    "_non_persistent_buffers_set", "_param_maps", "_parameters", "_state_dict_hooks", "_state_dict_pre_hooks",
    "_tensor_keys", "_value_estimator", "_call_cache", "training", "value_type",
}
def copied_functions() -> list:
    """What the fused steps copy besides the loss's class and its networks' classes (which
    ``learners.fast_paths`` finds from the built loss): the loss arithmetic's functions, the policy's
    distribution, tanh's and the kernels' forward and backward, the objective and the minibatch draw."""
    from learners.base import objective
    from learners.networks import MemberNormal, _EagerTanh, _pad_rows, _Tanh, _unpad_rows, stacked_linear
    from collectors.replay import sample_minibatch

    return [F.squared_error, F.weighted_log_likelihood, F.clipped_surrogate, F.ppo_ratio, F.mean,
            F.per_dimension_or_joint, F.per_member, MemberNormal, fast_tanh, _EagerTanh, _Tanh, stacked_linear,
            _pad_rows, _unpad_rows, kernel_ops.linear, kernel_ops._Linear, kernel_ops._gradients, objective,
            sample_minibatch]


def loss_refusal(loss) -> str | None:
    """Why the fused steps do not compute ``loss``'s steps (None: they do): they compute exactly
    ``SPGLoss`` or ``LogClipPPOLoss`` of a population with the settings they know (not a subclass,
    which may compute something else), the code they copy as they were checked against it
    (``learners.fast_paths``: the loss's class, its networks' and ``copied_functions``)."""
    from losses import LogClipPPOLoss, SPGLoss

    if type(loss) not in (SPGLoss, LogClipPPOLoss):
        return fast_paths.refusal(loss) or f"the loss is {type(loss).__name__}, not SPGLoss or LogClipPPOLoss themselves"
    if loss.members is None:
        return "the loss is not a population's (members=None)"
    name = type(loss).__name__
    public = {key for key in vars(loss) if not key.startswith("_")} - {"training", "value_type"}
    private = {key for key in vars(loss) if key.startswith("_")}
    unknown = sorted(public - KNOWN_SETTINGS[name]) + sorted(private - KNOWN_INTERNALS) + \
        [f"parameter {key}" for key in loss._parameters] + \
        [f"submodule {key}" for key in set(loss._modules) - KNOWN_MODULES[name]] + \
        [f"buffer {key}" for key in set(loss._buffers) - {"temperature"}]
    if unknown:
        return f"the {name} has {', '.join(unknown)}, which the fused steps do not know"
    return fast_paths.refusal(loss, copied_functions())


def loss_known(loss) -> bool:
    """Whether the fused steps compute ``loss``'s steps (``loss_refusal``)."""
    return loss_refusal(loss) is None


def critic_refusal(critic_net: torch.nn.Module) -> str | None:
    """Why ``FusedCritic`` does not compute this critic's step (None: it does)."""
    mlp = getattr(critic_net, "net", None)
    if type(critic_net) is not StackedCriticNet or type(mlp) is not StackedMLP:
        return f"the critic is a {type(critic_net).__name__}, not a StackedCriticNet of a StackedMLP"
    if not mlp.linear_output:
        return "the critic's output is not linear"
    return _kernels_refusal(critic_net, mlp, "critic")


def actor_refusal(actor_net: torch.nn.Module) -> str | None:
    """Why ``GaussianPolicyPass`` does not compute this actor's pass (None: it does)."""
    if type(actor_net) is not StackedGaussianPolicyNet or type(getattr(actor_net, "body", None)) is not StackedMLP:
        return f"the actor is a {type(actor_net).__name__}, not a StackedGaussianPolicyNet of a StackedMLP"
    return _kernels_refusal(actor_net, actor_net.body, "actor")


def critic_available(critic_net: torch.nn.Module) -> bool:
    return critic_refusal(critic_net) is None


def actor_available(actor_net: torch.nn.Module) -> bool:
    return actor_refusal(actor_net) is None


def _kernels_refusal(net: torch.nn.Module, mlp: StackedMLP, name: str) -> str | None:
    """The fused steps need the project's products (numerics=fma), ``net`` in float32 on the CPU and
    ``mlp``'s activation the paper's tanh."""
    if not kernels.active():
        return "the products are not the project's kernels (numerics other than fma, or no kernel library)"
    if mlp.activation is not fast_tanh:
        return f"the {name}'s activation is not tanh"
    if not all(p.device.type == "cpu" and p.dtype == torch.float32 for p in net.parameters()):
        return f"the {name} is not float32 on the CPU"
    return None


def _check_optimiser(optimiser, params: list[torch.Tensor], network: str) -> None:
    if [id(p) for p in optimiser.params] != [id(p) for p in params]:
        raise ValueError(f"the {network}'s optimiser must hold the {network}'s parameters in layer order")


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
        _check_optimiser(optimiser, self._params, "critic")

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
                    x = fast_tanh(x)
                    seen.append(x)
            value = x[:, :batch] if rows != batch else x
            error = target - value
            loss = F.mean(error.pow(2), True)
            value_mean = F.mean(value, True)
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


class GaussianPolicyPass:
    """The actor's forward pass with what its backward needs kept, and that backward: what
    ``StackedGaussianPolicyNet.forward`` and autograd compute, bit for bit."""

    def __init__(self, actor_net: StackedGaussianPolicyNet, optimiser):
        if not actor_available(actor_net):
            raise ValueError("GaussianPolicyPass needs a tanh StackedGaussianPolicyNet in float32 on the CPU "
                             "with numerics=fma")
        self.net = actor_net
        self.body = [(layer.weight, layer.bias) for layer in actor_net.body.layers]
        self.loc_head = (actor_net.loc_head.weight, actor_net.loc_head.bias)
        self.scale_head = (actor_net.scale_head.weight, actor_net.scale_head.bias)
        self.params = [p for pair in (*self.body, self.loc_head, self.scale_head) for p in pair]
        _check_optimiser(optimiser, self.params, "actor")
        self.optimiser = optimiser
        self.multiple = actor_net.act_rows

    def forward(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(loc, scale) of ``observation`` ``[R, B, obs]``, each ``[R, B, D]``."""
        batch = observation.shape[1]
        rows = batch + (-batch) % self.multiple
        x = observation if rows == batch else torch.nn.functional.pad(observation, (0, 0, 0, rows - batch))
        self._seen = [x]
        for weight, bias in self.body:
            x = fast_tanh(kernel_ops._forward(x, weight, bias))
            self._seen.append(x)
        self._loc = torch.tanh(kernel_ops._forward(x, *self.loc_head))
        self._scale_input = kernel_ops._forward(x, *self.scale_head)
        scale = torch.nn.functional.softplus(self._scale_input)
        self._batch, self._rows = batch, rows
        if rows == batch:
            return self._loc, scale
        return self._loc[:, :batch], scale[:, :batch]

    def backward_and_step(self, grad_loc: torch.Tensor, grad_scale: torch.Tensor) -> None:
        """The parameters' gradients from those of (loc, scale), then the optimiser's step."""
        if self._rows != self._batch:
            pad = (0, 0, 0, self._rows - self._batch)
            grad_loc, grad_scale = torch.nn.functional.pad(grad_loc, pad), torch.nn.functional.pad(grad_scale, pad)
        grad_loc = torch.ops.aten.tanh_backward(grad_loc, self._loc)
        grad_scale = torch.ops.aten.softplus_backward(grad_scale, self._scale_input, 1.0, 20.0)
        h = self._seen[-1]
        grads = [kernel_ops._weight_grad(grad_loc, h), kernel_ops.colsum(grad_loc),
                 kernel_ops._weight_grad(grad_scale, h), kernel_ops.colsum(grad_scale)]
        grad = kernel_ops._input_grad(grad_loc, self.loc_head[0]) + kernel_ops._input_grad(grad_scale, self.scale_head[0])
        body = []
        for i in range(len(self.body) - 1, -1, -1):
            weight = self.body[i][0]
            grad = torch.ops.aten.tanh_backward(grad, self._seen[i + 1])
            body[:0] = [kernel_ops._weight_grad(grad, self._seen[i]), kernel_ops.colsum(grad)]
            if i > 0:
                grad = kernel_ops._input_grad(grad, weight)
        for p, g in zip(self.params, body + grads):
            p.grad = g
        self._seen = self._loc = self._scale_input = None
        self.optimiser.step()


def normal_log_prob(loc: torch.Tensor, scale: torch.Tensor, value: torch.Tensor):
    """``learners.networks.MemberNormal.log_prob`` with what its backward needs: (log-probabilities,
    a function from their gradient to those of (loc, scale) as autograd computes them)."""
    difference = value - loc
    var = scale ** 2
    numerator = -(difference ** 2)
    denominator = 2 * var
    log_prob = numerator / denominator - F.per_member(torch.log, scale) - _LOG_SQRT_2PI

    def backward(grad: torch.Tensor, grad_scale_first: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``grad_scale_first``: a gradient of ``scale`` from a later use (the entropy's logarithm),
        which autograd adds first."""
        grad_numerator = grad / denominator
        grad_denominator = -grad * ((numerator / denominator) / denominator)
        through_log = (-grad) / scale
        if grad_scale_first is not None:
            through_log = grad_scale_first + through_log
        grad_scale = through_log + (grad_denominator * 2) * (scale.pow(1.0) * 2.0)
        grad_loc = -((-grad_numerator) * (difference.pow(1.0) * 2.0))
        return grad_loc, grad_scale

    return log_prob, backward


class FusedSPGActor:
    """One SPG actor step (``SPGLoss.actor_loss``, then ``objective``, backward and Adam), bit for bit:
    the candidates scored by the critic without a graph, the policy's log-likelihood of the best one
    (weighted by its Q gain under SPG-p) and its gradient as autograd takes it."""

    def __init__(self, loss, policy: GaussianPolicyPass, critic_net: torch.nn.Module, active: torch.Tensor):
        if loss.entropy_coeff != 0 or loss.members is None:
            raise ValueError("FusedSPGActor computes SPG without an entropy bonus, for a population")
        self.loss, self.policy, self.critic_net, self.active = loss, policy, critic_net, active
        self.action_key = loss.tensor_keys.action
        self.critic_keys = list(loss.qvalue_network.in_keys)
        self.actor_key = loss.actor_network.in_keys[0]

    def step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One Adam step of the actor on the minibatch ``batch`` ({key: [R, B, ...]}); returns the
        step's diagnostics, one value per member."""
        loss = self.loss
        action = batch[self.action_key]
        noise = loss._perturbations(action)  # drawn where SPGLoss.draw draws them
        loc, scale = self.policy.forward(batch[self.actor_key])
        with torch.no_grad():
            temperature = loss.temperature.to(loc.dtype).reshape(-1, *[1] * (noise.dim() - 1))
            candidates = F.spg_candidates(action, loc, noise, temperature, loss.sample_around)
            count = candidates.shape[-2]
            inputs = [candidates if key == self.action_key else _repeat(batch[key], count) for key in self.critic_keys]
            scores = self.critic_net(*inputs).squeeze(-1)
            target, index = F.best_candidate(candidates, scores)
            q_target = scores.gather(-1, index.unsqueeze(-1))
            q_baseline = scores[..., 1:2] if loss.baseline == "mean" else scores[..., 0:1]
            weight = q_target - q_baseline if loss.prioritised else None
            log_prob, log_prob_backward = normal_log_prob(loc, scale, target)
            joint = loss.joint_log_prob
            terms = F.per_dimension_or_joint(log_prob, joint)
            weighted = terms if weight is None else weight * terms
            members = weighted.shape[0]
            loss_objective = -F.mean(weighted, True)
            entropy = F.mean(F.per_dimension_or_joint(_entropy(loc, scale), joint), True)
            entries = {
                "loss_objective": loss_objective,
                "loss_entropy": -loss.entropy_coeff * entropy,
                "entropy": entropy,
                "weight_mean": torch.ones(q_target.shape[:-2]) if weight is None else F.mean(weight, True),
                "q_target": F.mean(q_target, True),
                "q_gain": F.mean(q_target - q_baseline, True),
                "target_is_action": F.mean((index == 0).float(), True),
                "target_is_mean": F.mean((index == 1).float(), True),
                "temperature": loss.temperature.float(),
            }
            # backward: d/d terms of sum_r active_r * -mean(weight * terms)
            size = weighted[0].numel()
            grad = (-self.active).unsqueeze(-1).expand(members, size) / size
            grad = grad.reshape(weighted.shape)
            if weight is not None:
                grad = grad * weight
            if joint:
                grad = grad.expand(log_prob.shape)
            grad_loc, grad_scale = log_prob_backward(grad)
            self.policy.backward_and_step(grad_loc, grad_scale)
        return entries


def _entropy(loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """The policy's entropy per dimension (``MemberNormal.entropy``)."""
    return MemberNormal(loc, scale, validate_args=False).entropy()


class FusedPPOActor:
    """One PPO actor step (``LogClipPPOLoss.actor_loss``, then ``objective``, backward and Adam), bit for
    bit: the clipped surrogate in linear or log space, the entropy bonus, and their gradients as
    autograd takes them."""

    def __init__(self, loss, policy: GaussianPolicyPass, active: torch.Tensor):
        if loss.members is None:
            raise ValueError("FusedPPOActor computes PPO for a population")
        self.loss, self.policy, self.active = loss, policy, active
        keys = loss.tensor_keys
        self.keys = (loss.actor_network.in_keys[0], keys.action, keys.sample_log_prob, keys.advantage)

    def step(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """One Adam step of the actor on the minibatch ``batch`` ({key: [R, B, ...]}); returns the
        step's diagnostics, one value per member."""
        loss = self.loss
        observation, action, old_log_prob, advantage = (batch[key] for key in self.keys)
        loc, scale = self.policy.forward(observation)
        with torch.no_grad():
            joint = loss.joint_log_prob
            per_dimension, log_prob_backward = normal_log_prob(loc, scale, action)
            log_prob = F.per_dimension_or_joint(per_dimension, joint)
            if old_log_prob.shape != log_prob.shape:
                raise ValueError(f"{self.keys[2]} has shape {tuple(old_log_prob.shape)} but the policy's "
                                 f"log-probabilities have shape {tuple(log_prob.shape)}")
            ratio = F.ppo_ratio(log_prob, old_log_prob, loss.ratio_space, True)
            low, high = F.clip_bounds(loss.clip_epsilon, loss.ratio_space)
            unclipped = ratio * advantage
            bounded = ratio.clamp(low, high)
            clipped = bounded * advantage
            objective = torch.minimum(unclipped, clipped)
            members = objective.shape[0]
            entropy_terms = F.per_dimension_or_joint(_entropy(loc, scale), joint)
            entropy = F.mean(entropy_terms, True)
            entries = {
                "loss_objective": -F.mean(objective, True),
                "loss_entropy": -loss.entropy_coeff * entropy,
                "entropy": entropy,
                "clip_fraction": F.mean((clipped < unclipped).float(), True),
                "approx_kl": F.approx_kl(log_prob, old_log_prob, True),
                "ratio_mean": F.mean(ratio, True),
                "advantage_mean": F.mean(advantage, True),
            }
            # backward: d/d (loc, scale) of sum_r active_r * (loss_objective_r [+ loss_entropy_r])
            size = objective[0].numel()
            grad = ((-self.active).unsqueeze(-1).expand(members, size) / size).reshape(objective.shape)
            equal = unclipped == clipped
            halved = torch.where(equal, grad / 2, grad)
            grad_unclipped = halved.masked_fill(unclipped > clipped, 0)
            grad_clipped = halved.masked_fill_(unclipped < clipped, 0)
            inside = (ratio >= low).logical_and_(ratio <= high)
            grad_ratio = (torch.where(inside, grad_clipped * advantage, torch.zeros((), dtype=grad.dtype))
                          + grad_unclipped * advantage)
            grad_log_ratio = grad_ratio * ratio if loss.ratio_space == "linear" else grad_ratio
            if joint:
                grad_log_ratio = grad_log_ratio.expand(per_dimension.shape)
            grad_entropy_scale = None
            if loss.entropy_coeff:
                count = entropy_terms[0].numel()
                grad_entropy = ((self.active * -loss.entropy_coeff).unsqueeze(-1).expand(members, count) / count)
                grad_entropy = grad_entropy.reshape(entropy_terms.shape)
                if joint:
                    grad_entropy = grad_entropy.expand(scale.shape)
                grad_entropy_scale = grad_entropy / scale
            grad_loc, grad_scale = log_prob_backward(grad_log_ratio, grad_entropy_scale)
            self.policy.backward_and_step(grad_loc, grad_scale)
        return entries
