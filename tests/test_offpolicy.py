"""SAC and TD3 (TorchRL's losses) in the population pipeline, and proportional prioritised replay.

The losses are TorchRL's; what is checked here is the wiring: values equal TorchRL's plain
losses for a population of one, each loss term's gradient reaches only its own networks,
members do not mix, target networks move by ``tau``, and runs train, resume exactly and report
through ``train.py``.
"""

import json

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch.distributions.utils import _standard_normal
from torchrl.data import Bounded, LazyTensorStorage, TensorDictReplayBuffer
from torchrl.modules import ProbabilisticActor, TanhNormal
from torchrl.objectives import CrossQLoss, SACLoss, SoftUpdate, TD3Loss, TQCLoss

from collectors.prioritised import WEIGHT_KEY, ProportionalSampler
from engine.config import ConfigError
from engine.evaluation import load_policy, make_policy
from engine.setup import make_env, make_generators, make_learner
from learners.td import crossq, td3
from learners.base import MetricTotals
from losses.td import ACTION_NOISE_KEY, DrawnTanhNormal
from losses.td3 import SMOOTHING_KEY
from losses.tqc import quantile_huber_loss
from engine.runner import train_population
from tests.test_config import load
from tests.test_resilience import interrupted_after
from tests.test_train import read_rows, run_train

A, B = 2067791, 5468063
FAST = ["episodes=4", "algo.td.warmup_episodes=1", "algo.td.updates_per_step=0.05", "progress=false", "logger=none"]


def training(algo, *extra, seeds=(A, B)):
    cfg = load(f"algo={algo}", "er=memory", f"seeds=[{','.join(map(str, seeds))}]", *extra)
    torch.manual_seed(0)
    generators = make_generators(tuple(seeds))
    return cfg, make_learner(cfg, make_env(cfg, tuple(seeds)), generators)


def solo_and_resumed_pair(run: list[str], folder) -> str:
    """``run`` trained as seed B alone, and as the pair (B, A) interrupted after episode 3 and resumed (checkpoints
    every 2 episodes): the pair resumed at episode 2 and member B's metrics.csv equals the solo run's, which is
    returned."""
    train_population(load(*run, f"seed={B}"), folder / "solo")
    with interrupted_after(3):
        train_population(load(*run, f"seeds=[{B},{A}]"), folder / "pair")
    summaries = train_population(load(*run, f"seeds=[{B},{A}]"), folder / "pair")
    assert [s["resumed_at"] for s in summaries] == [2, 2]
    solo = (folder / "solo" / "metrics.csv").read_text()
    assert (folder / "pair" / f"seed{B}" / "metrics.csv").read_text() == solo
    return solo


def transitions(members, n, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": torch.rand(members, n, 6, generator=g),
        "action": torch.rand(members, n, 2, generator=g) * 2 - 1,
        "next": TensorDict({"observation": torch.rand(members, n, 6, generator=g),
                            "reward": torch.rand(members, n, 1, generator=g),
                            "done": torch.zeros(members, n, 1, dtype=torch.bool),
                            "terminated": torch.zeros(members, n, 1, dtype=torch.bool)}, batch_size=[members, n]),
    }, batch_size=[members, n])


# --------------------------------------------------------------------------- the losses
def _plain_actor(t):
    """The learner's actor network as TorchRL's own TanhNormal actor (drawing from torch's generator)."""
    return ProbabilisticActor(TensorDictModule(t.networks.actor_net, ["observation"], ["loc", "scale"]),
                              in_keys=["loc", "scale"], distribution_class=TanhNormal,
                              distribution_kwargs={"low": -1.0, "high": 1.0})


def _with_torchrl_draws(plain, loss, data):
    """TorchRL's loss on ``data``, then ours given the N(0, I) draws TorchRL made, in its order: the
    target's action, then the actor loss's; and those draws."""
    torch.manual_seed(1)
    theirs = plain(data.clone())
    torch.manual_seed(1)
    mine = data.clone()
    mine.set(("next", ACTION_NOISE_KEY), _standard_normal((1, 64, 2), dtype=torch.float32, device="cpu"))
    mine.set(ACTION_NOISE_KEY, _standard_normal((1, 64, 2), dtype=torch.float32, device="cpu"))
    noise = mine.select(ACTION_NOISE_KEY, ("next", ACTION_NOISE_KEY)).clone()
    return theirs, loss(mine), noise


def test_sac_of_a_population_of_one_equals_torchrl_sac_loss():
    """MemberSACLoss (per-member temperature, per-transition terms averaged per member, noise drawn
    ahead) gives TorchRL's SACLoss (reduction="mean", one scalar temperature, TanhNormal drawing
    from the global generator) on the same networks and the same N(0, I) draws."""
    cfg, t = training("sac", seeds=(A,))
    plain = SACLoss(_plain_actor(t), t.networks.qvalues, num_qvalue_nets=2, loss_function="l2", alpha_init=1.0,
                    target_entropy=-2.0, deactivate_vmap=True)
    plain.make_value_estimator(gamma=cfg.gamma)
    SoftUpdate(plain, tau=0.005)
    # The same weights: ours were initialised from the generators; copy the loss's stacked Q-networks.
    plain.qvalue_network_params.data.copy_(t.loss.qvalue_network_params.data)
    plain.target_qvalue_network_params.data.copy_(t.loss.target_qvalue_network_params.data)
    data = transitions(1, 64)
    theirs, ours, noise = _with_torchrl_draws(plain, t.loss, data)
    for key in ("loss_actor", "loss_qvalue", "loss_alpha"):
        torch.testing.assert_close(ours[key].mean(), theirs[key], rtol=1e-6, atol=1e-6)
    assert not torch.equal(t.loss(data.clone().update(noise.apply(torch.neg)))["loss_actor"], ours["loss_actor"])


def test_tqc_of_a_population_of_one_equals_torchrl_tqc_loss():
    """MemberTQCLoss (per-member temperature, noise drawn ahead) gives TorchRL's TQCLoss on the same
    quantile critics and the same N(0, I) draws: the pooled target without its highest quantiles,
    the quantile Huber critic loss, the actor's mixture mean."""
    cfg, t = training("tqc", "algo.tqc.quantiles=5", "algo.tqc.drop_per_critic=1", seeds=(A,))
    plain = TQCLoss(_plain_actor(t), t.networks.qvalues, num_qvalue_nets=2, top_quantiles_to_drop_per_net=1,
                    alpha_init=1.0, target_entropy=-2.0, deactivate_vmap=True, reduction="mean")
    plain.make_value_estimator(gamma=cfg.gamma)
    SoftUpdate(plain, tau=0.005)
    plain.qvalue_network_params.data.copy_(t.loss.qvalue_network_params.data)
    plain.target_qvalue_network_params.data.copy_(t.loss.target_qvalue_network_params.data)
    assert t.loss.qvalue_network_params.flatten_keys(".")["module.net.layers.2.weight"].shape[-2] == 5  # quantiles
    data = transitions(1, 64)
    theirs, ours, _ = _with_torchrl_draws(plain, t.loss, data)
    for key in ("loss_actor", "loss_qvalue", "loss_alpha"):
        torch.testing.assert_close(ours[key].mean(), theirs[key], rtol=1e-6, atol=1e-6)


def _torchrl_quantile_huber(quantiles, targets):
    """TorchRL's TQCLoss.qvalue_v2_loss critic term per Q-network and transition, as it writes it."""
    delta = targets.unsqueeze(0).unsqueeze(-2) - quantiles.unsqueeze(-1)
    huber = torch.where(delta.abs() <= 1, 0.5 * delta.square(), delta.abs() - 0.5)
    n = quantiles.shape[-1]
    fractions = ((torch.arange(n, dtype=quantiles.dtype) + 0.5) / n).view(*([1] * (delta.ndim - 2)), n, 1)
    return ((fractions - (delta.detach() < 0).to(quantiles.dtype)).abs() * huber).mean((-1, -2)), \
        delta.detach().abs().mean((-1, -2))


def test_quantile_huber_loss_equals_torchrl_expression_and_is_sliced_per_transition():
    """The fused TQC critic loss: TorchRL's values and gradients (to float32 rounding), including
    errors beyond the Huber threshold on both sides and exact ties (delta = 0); any slicing of the
    minibatch gives the same bits, and a member's result does not depend on the others."""
    g = torch.Generator().manual_seed(0)
    quantiles = (torch.randn(2, 3, 40, 5, generator=g) * 2).requires_grad_()
    targets = torch.randn(3, 40, 7, generator=g) * 2
    targets[0, 0, :5] = quantiles[0, 0, 0].detach()  # ties
    theirs, their_td = _torchrl_quantile_huber(quantiles, targets)
    (their_grad,) = torch.autograd.grad(theirs.sum(), quantiles)
    ours, our_td = quantile_huber_loss(quantiles, targets.unsqueeze(0))
    (our_grad,) = torch.autograd.grad(ours.sum(), quantiles)
    assert ours.shape == our_td.shape == (2, 3, 40)
    torch.testing.assert_close(ours, theirs, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(our_td, their_td, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(our_grad, their_grad, rtol=1e-6, atol=1e-8)
    for chunk in (1, 2 * 5 * 7 * 3, 10 ** 9):  # one transition per slice, a few, all at once
        sliced, sliced_td = quantile_huber_loss(quantiles, targets.unsqueeze(0), chunk=chunk)
        assert torch.equal(sliced, ours) and torch.equal(sliced_td, our_td)
    alone, _ = quantile_huber_loss(quantiles[:, 1:2], targets[1:2].unsqueeze(0))
    assert torch.equal(alone, ours[:, 1:2])


class _Solo(torch.nn.Module):
    """A population of one as TorchRL's losses expect a network: over ``[B, ...]``, no member dim."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, *inputs):
        out = self.net(*(x.unsqueeze(0) for x in inputs))
        return tuple(o.squeeze(0) for o in out) if isinstance(out, tuple) else out.squeeze(0)


class _GivenNoise(DrawnTanhNormal):
    """TorchRL's CrossQ draws the next action unreparameterised: here from the given noise too."""

    def sample_and_log_prob(self, sample_shape=()):
        return self.rsample_and_log_prob(sample_shape)


def test_crossq_of_a_population_of_one_equals_torchrl_crossq_loss():
    """MemberCrossQLoss (current and next state-action pairs joined along the minibatch dimension,
    per-member temperature) gives TorchRL's CrossQLoss (joined along its batch dimension) on the
    same batch-normalised critics, actor and noise: critic loss, then actor loss against the
    critics in evaluation mode (running statistics updated by the critic pass), temperature loss."""
    cfg, t = training("crossq", seeds=(A,))
    actor = ProbabilisticActor(TensorDictModule(_Solo(t.networks.actor_net), ["observation"], ["loc", "scale"]),
                               in_keys={"loc": "loc", "scale": "scale", "noise": ACTION_NOISE_KEY},
                               distribution_class=_GivenNoise, distribution_kwargs={"low": -1.0, "high": 1.0})
    qvalues = [TensorDictModule(_Solo(q), ["observation", "action"], ["state_action_value"])
               for q in t.networks.qvalue_nets]
    plain = CrossQLoss(actor, qvalues, num_qvalue_nets=2, loss_function="l2", alpha_init=1.0, target_entropy=-2.0,
                       deactivate_vmap=True)
    plain.make_value_estimator(gamma=cfg.gamma)
    data = transitions(1, 64)
    t.loss.draw(data)
    theirs, mine = plain(data[0].clone()), t.loss(data.clone())
    for key in ("loss_qvalue", "loss_actor", "loss_alpha"):
        torch.testing.assert_close(mine[key].mean(), theirs[key], rtol=1e-6, atol=1e-6)
    stats = [v for v in t.loss.qvalue_network_params.values(True, True) if not v.requires_grad]
    assert stats and all(torch.equal(a, b) for a, b in zip(
        stats, [v for v in plain.qvalue_network_params.values(True, True) if not v.requires_grad]))
    assert not torch.equal(stats[0][:, 0], torch.zeros_like(stats[0][:, 0]))  # the running means moved


def test_stacked_batch_norm_is_torch_batch_norm_per_member():
    """Training mode: each member normalised by its own rows' statistics, running estimates updated
    as torch's (momentum, unbiased variance); evaluation mode: by the running estimates."""
    from learners.networks import StackedBatchNorm

    g = torch.Generator().manual_seed(0)
    norm = StackedBatchNorm(3, 4, momentum=0.1, eps=1e-3)
    with torch.no_grad():
        norm.weight.copy_(torch.rand(3, 4, generator=g) + 0.5)
        norm.bias.copy_(torch.rand(3, 4, generator=g))
    x = torch.randn(3, 10, 4, generator=g) * 3 + 1
    out = norm(x)
    for r in range(3):
        mean, var = torch.zeros(4), torch.ones(4)
        expected = torch.nn.functional.batch_norm(x[r], mean, var, norm.weight[r], norm.bias[r], training=True,
                                                  momentum=0.1, eps=1e-3)
        torch.testing.assert_close(out[r], expected, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(norm.running_mean[r], mean)
        torch.testing.assert_close(norm.running_var[r], var)
    norm.eval()
    torch.testing.assert_close(norm(x)[1], torch.nn.functional.batch_norm(
        x[1], norm.running_mean[1], norm.running_var[1], norm.weight[1], norm.bias[1], eps=1e-3), rtol=1e-5, atol=1e-5)


def test_td3_with_drawn_smoothing_noise_equals_torchrl_td3_loss():
    """MemberTD3Loss's target (smoothing noise drawn ahead, added by the actor) and actor loss are
    TorchRL's TD3Loss's, bit for bit, given the same draw."""
    cfg, t = training("td3", seeds=(A,))
    plain = TD3Loss(TensorDictModule(t.networks.actor_net, ["observation"], ["action"]), t.networks.qvalues,
                    action_spec=Bounded(-1.0, 1.0, (2,)), num_qvalue_nets=2, policy_noise=0.2, noise_clip=0.5,
                    loss_function="l2", reduction="none", deactivate_vmap=True)
    plain.make_value_estimator(gamma=cfg.gamma)
    SoftUpdate(plain, tau=0.005)
    for name in ("qvalue_network_params", "target_qvalue_network_params", "target_actor_network_params"):
        for theirs, ours in zip(getattr(plain, name).values(True, True), getattr(t.loss, name).values(True, True),
                                strict=True):  # the same leaves; the actor's sit one module deeper in ours
            theirs.data.copy_(ours.data)
    data = transitions(1, 64)
    torch.manual_seed(1)
    theirs = plain.value_loss(data.clone())[0]
    torch.manual_seed(1)
    mine = data.clone()
    mine.set(("next", SMOOTHING_KEY), (torch.randn(1, 64, 2) * 0.2).clamp(-0.5, 0.5))
    mine.set(SMOOTHING_KEY, torch.zeros(1, 64, 2))
    assert torch.equal(t.loss.value_loss(mine)[0], theirs)
    assert torch.equal(t.loss.actor_loss(mine)[0], plain.actor_loss(data.clone())[0])


def test_td3_preact_penalty_adds_the_mean_square_of_the_pre_tanh_action():
    """algo.td3.preact_penalty=c: each member's actor loss is TorchRL's plus c * mean(u^2), u the
    pre-tanh actions at the minibatch's states (u = atanh(mu), checked in float64), and the extra
    gradient reaches the actor's weights (the ones its optimiser steps)."""
    _, plain = training("td3", "algo.td3.preact_penalty=0")
    _, penalised = training("td3", "algo.td3.preact_penalty=0.5")
    data = transitions(2, 64)
    plain.loss.draw(data)
    base, extra = td3.actor_losses(plain.phases, data), td3.actor_losses(penalised.phases, data)
    with torch.no_grad():
        u = torch.atanh(penalised.networks.actor_net(data["observation"]).double())
    torch.testing.assert_close((extra - base).double(), 0.5 * u.square().mean((1, 2)), rtol=1e-5, atol=1e-6)
    extra.sum().backward()
    base.sum().backward()
    grads = [(p.grad, q.grad) for p, q in zip(penalised.optimisers.actor.params, plain.optimisers.actor.params)]
    assert all(g is not None for pair in grads for g in pair) and not all(torch.equal(a, b) for a, b in grads)


def module_then_fused(step, mode: str):
    """``step(False), step(True)`` (through the loss module, then fused) under numerics ``mode``'s
    products (fma: the project's kernels; portable: torch's), the process's own restored after."""
    from learners import kernels

    previous = kernels.active()
    try:
        if kernels.use(mode == "fma"):
            pytest.skip("the kernels cannot be built here")
        return step(False), step(True)
    finally:
        kernels.use(previous)


@pytest.mark.parametrize("mode", ["fma", "portable"])
@pytest.mark.parametrize("extra", [[], ["er=prioritised", "algo.td.n_step=3", "algo.td.loss_function=smooth_l1"],
                                   ["algo=bro", "er=prioritised", "algo.td.critic_width=48"],
                                   ["algo=droq", "er=prioritised"], ["algo=droq", "algo.td.critic_layer_norm=false"],
                                   ["algo=tqc"], ["algo=tqc", "er=prioritised", "algo.td.n_step=3", "algo.tqc.critics=3"],
                                   ["algo.td.pessimism=0"], ["er=prioritised", "algo.td.pessimism=-0.5"]])
def test_fused_sac_step_is_the_torchrl_loss_bit_for_bit(mode, extra):
    """The fused SAC step (plain tensors, the Q-networks in one stacked pass) gives TorchRL's loss
    module's losses, priorities and gradients bit for bit: with importance weights, n-step
    discounts, another critic loss, BRO's residual Q-networks, DroQ's (dropout masks drawn from the
    members' generators in the loss module's order; with and without layer norm), TQC's (its pooled,
    truncated quantile targets), the Q-networks combined by algo.td.pessimism, in both numerics that
    switch after torch loads."""
    cfg, t = training("sac", *extra, seeds=(A, B, 7))
    assert t.phases.fused
    data = transitions(3, 256)
    if "algo=droq" in extra:
        assert t.loss.generators and all(d.active for d in t.loss.qvalue_network.module.net.dropouts)
    g = torch.Generator().manual_seed(5)
    if "er=prioritised" in extra:
        data.set("priority_weight", torch.rand(3, 256, generator=g))
        data.set("steps_to_next_obs", torch.randint(1, 4, (3, 256, 1), generator=g))
    t.loss.draw(data)
    loss = t.loss
    params = [*loss.actor_network_params.values(True, True), loss.log_alpha, *loss.qvalue_network_params.values(True, True)]

    generators = t.loss.generators
    drawn_from = [g.get_state() for g in generators]  # DroQ draws its dropout masks in the step

    def step(fused):
        t.phases.fused = fused
        for p in params:
            p.grad = None
        for g, state in zip(generators, drawn_from):
            g.set_state(state)
        losses, priority = t.phases.steps_of.losses(t.phases, data.clone())
        (sum(losses.values()) * torch.tensor([1.0, 2.0, 3.0])).sum().backward()
        return losses, priority, [p.grad.clone() for p in params]

    (theirs, their_priority, their_grads), (ours, our_priority, our_grads) = module_then_fused(step, mode)
    assert set(ours) == set(theirs) and all(torch.equal(ours[k], theirs[k]) for k in theirs)
    assert torch.equal(our_priority, their_priority)
    assert all(a.any() for a in our_grads) and all(torch.equal(a, b) for a, b in zip(our_grads, their_grads))


@pytest.mark.parametrize("mode", ["fma", "portable"])
@pytest.mark.parametrize("extra", [[], ["er=prioritised", "algo.td.n_step=3", "algo.td.loss_function=smooth_l1",
                                        "algo.td3.preact_penalty=0"],
                                   ["algo.td.critic_dropout=0.1", "algo.td.critic_layer_norm=true"]])
def test_fused_td3_steps_are_the_torchrl_loss_bit_for_bit(mode, extra):
    """The fused TD3 steps (plain tensors, the Q-networks in one stacked pass, the actor scored by the
    first Q-network only) give TorchRL's TD3Loss's critic and actor losses, priorities and gradients
    bit for bit: with the pre-tanh penalty and without, importance weights, n-step discounts, another
    critic loss, DroQ-style Q-networks (their dropout masks drawn in the module's order, the members'
    generators left where the module leaves them)."""
    cfg, t = training("td3", *extra, seeds=(A, B, 7))
    assert t.phases.fused
    data = transitions(3, 256)
    g = torch.Generator().manual_seed(5)
    if "er=prioritised" in extra:
        data.set("priority_weight", torch.rand(3, 256, generator=g))
        data.set("steps_to_next_obs", torch.randint(1, 4, (3, 256, 1), generator=g))
    t.loss.draw(data)
    critic = list(t.loss.qvalue_network_params.values(True, True))
    actor = list(t.loss.actor_network_params.values(True, True))
    states = [g.get_state() for g in t.loss.generators]  # dropout masks are drawn in the step

    def step(fused):
        t.phases.fused = fused
        for p in critic + actor:
            p.grad = None
        for g, state in zip(t.loss.generators, states):
            g.set_state(state)
        loss_qvalue, priority = td3.critic_losses(t.phases, data.clone())
        (loss_qvalue * torch.tensor([1.0, 2.0, 3.0])).sum().backward()
        loss_actor = td3.actor_losses(t.phases, data.clone())
        (loss_actor * torch.tensor([3.0, 1.0, 2.0])).sum().backward()
        drawn = [g.get_state() for g in t.loss.generators]  # the next step's masks start there
        return [loss_qvalue, priority, loss_actor] + [p.grad.clone() for p in critic + actor] + drawn

    theirs, ours = module_then_fused(step, mode)
    assert all(a.any() for a in ours[3:3 + len(critic + actor)])
    assert all(torch.equal(a, b) for a, b in zip(ours, theirs, strict=True))


@pytest.mark.parametrize("mode", ["fma", "portable"])
@pytest.mark.parametrize("extra", [[], ["algo.td.n_step=3", "algo.td.loss_function=smooth_l1"]])
def test_fused_crossq_steps_are_the_torchrl_loss_bit_for_bit(mode, extra):
    """The fused CrossQ steps (every Q-network and member in one batch-normalised pass) give the loss
    module's critic loss, priorities, running estimates, actor and temperature losses and every
    gradient bit for bit (TorchRL's CrossQLoss.actor_loss, MemberCrossQLoss.qvalue_loss)."""
    cfg, t = training("crossq", *extra, seeds=(A, B, 7))
    assert t.phases.fused
    data = transitions(3, 256)
    if extra:
        g = torch.Generator().manual_seed(5)
        data.set("steps_to_next_obs", torch.randint(1, 4, (3, 256, 1), generator=g))
    t.loss.draw(data)
    critic = [p for p in t.loss.qvalue_network_params.values(True, True) if p.requires_grad]
    statistics = [p for p in t.loss.qvalue_network_params.values(True, True) if not p.requires_grad]
    actor = list(t.loss.actor_network_params.values(True, True)) + [t.loss.log_alpha]
    before = [p.clone() for p in statistics]

    def step(fused):
        t.phases.fused = fused
        for p, value in zip(statistics, before):
            p.copy_(value)
        for p in critic + actor:
            p.grad = None
        totals = MetricTotals()
        t.phases.optimisers.critic.step = t.phases.optimisers.actor.step = lambda: None  # gradients only
        priority = crossq.step(t.phases, data.clone(), t.phases.policy_delay - 1, totals)  # with an actor step
        running = [p.clone() for p in statistics]
        return [priority, *running, *[p.grad.clone() for p in critic + actor],
                *[torch.stack(v) for v in totals.values.values()]]

    theirs, ours = module_then_fused(step, mode)
    assert not all(torch.equal(a, b) for a, b in zip(before, ours[1:1 + len(statistics)]))  # estimates moved
    assert all(g.any() for g in ours[1 + len(statistics):1 + len(statistics) + len(critic + actor)])
    assert all(torch.equal(a, b) for a, b in zip(ours, theirs, strict=True))


@pytest.mark.parametrize("recipe", [["algo=sac", "algo.td.updates_per_step=0.25", "episodes=2"],
                                    pytest.param(["algo=crossq", "er=memory", "algo.td.updates_per_step=0.25",
                                                  "episodes=2"], marks=pytest.mark.slow),
                                    pytest.param(["algo=td3", "algo.td.updates_per_step=0.25", "episodes=2"],
                                                 marks=pytest.mark.slow),
                                    ["algo=tqc", "algo.td.updates_per_step=0.25", "episodes=2"],
                                    ["algo=bro", "algo.td.updates_per_step=0.1", "episodes=4", "algo.td.critic_width=32",
                                     "algo.td.reset_every=3"],
                                    ["algo=droq", "algo.td.updates_per_step=0.25", "episodes=2"],
                                    pytest.param(["algo=sac", "algo.td.updates_per_step=0.25", "episodes=2",
                                                  "algo.td.privileged_critic=true", "algo.td.critic_history=2"],
                                                 marks=pytest.mark.slow)])
def test_a_run_with_the_fused_sac_step_is_a_run_through_the_loss_module(tmp_path, monkeypatch, recipe):
    """Whole runs (prioritised replay but for CrossQ, two members, 50-60 gradient steps; TD3's; TQC's; CrossQ's; BRO's Q-networks with a
    reset; DroQ's; SAC's Q-networks reading the car's true state and past steps, which TorchRL's SACLoss
    passes them as two more keys): byte-identical learning curves and weights with and without the fused step."""
    from learners.td import learner

    cfg = load("er=prioritised", *recipe, f"seeds=[{A},{B}]", "algo.td.warmup_episodes=1",
               "progress=false", "logger=none", "checkpoint_every=0")
    outputs = {}
    for fused in (True, False):
        monkeypatch.setattr(learner, "FUSED", fused)
        out = tmp_path / str(fused)
        train_population(cfg, out)
        outputs[fused] = sorted((p.relative_to(out), p.read_bytes()) for p in out.rglob("*")
                                if p.is_file() and p.suffix in (".csv", ".pt") and "checkpoint" not in p.name)
    assert outputs[True] and outputs[True] == outputs[False]


def test_fused_sac_step_is_taken_only_where_it_computes_the_loss():
    for algo, extra, fused in [("sac", [], True), ("crossq", [], True), ("td3", [], True), ("tqc", [], True),
                               ("droq", [], True), ("sac", ["compile=true"], False), ("bro", [], True)]:
        assert training(algo, *extra)[1].phases.fused is fused, (algo, extra)


@pytest.mark.parametrize("algo", ["sac", "tqc", "crossq", "td3"])
def test_each_loss_term_reaches_only_its_own_networks_and_members_do_not_mix(algo):
    cfg, t = training(algo)
    data = transitions(2, 32)
    actor = t.optimisers.actor.params
    critic = t.optimisers.critic.params

    keys = set(data.keys(True, True))
    t.loss.draw(data)  # the members' noise, kept for every call below
    noise = [key for key in data.keys(True, True) if key not in keys]
    assert noise

    def grads(term, batch):
        for p in actor + critic:
            p.grad = None
        if algo in ("sac", "tqc", "crossq"):
            out = t.loss(batch.clone())[term]
        else:
            out = (t.loss.value_loss if term == "loss_qvalue" else t.loss.actor_loss)(batch.clone())[0]
        out.mean(-1).sum().backward()
        return ([p.grad.clone() if p.grad is not None else None for p in actor],
                [p.grad.clone() if p.grad is not None else None for p in critic])

    a, c = grads("loss_qvalue", data)
    assert all(g is None or not g.any() for g in a) and all(g is not None and g.any() for g in c)
    a, c = grads("loss_actor", data)
    assert all(g is None or not g.any() for g in c)
    assert all(g is not None and g.any() for g in a[:len(list(t.networks.actor_net.parameters()))])
    if algo in ("sac", "tqc", "crossq"):
        a, c = grads("loss_alpha", data)
        assert a[-1] is not None and a[-1].ne(0).all()  # log_alpha, one per member
        assert all(g is None or not g.any() for g in a[:-1] + c)
    # Member 1's data changes: member 0's gradients do not.
    a0, c0 = grads("loss_qvalue", data)
    other, changed = data.clone(), transitions(2, 32, seed=9)
    for key in noise:
        changed.set(key, data.get(key))
    other[1] = changed[1]
    a1, c1 = grads("loss_qvalue", other)
    for g0, g1 in zip(c0, c1):  # Q-network parameters are [Q-net, member, ...]
        torch.testing.assert_close(g0[:, 0], g1[:, 0], rtol=0, atol=0)
        assert not torch.equal(g0[:, 1], g1[:, 1])


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_targets_follow_the_online_networks_by_tau(algo):
    cfg, t = training(algo, "algo.td.tau=0.25")
    before = t.loss.target_qvalue_network_params.clone()
    totals = MetricTotals()
    episode = cfg.algo.td.warmup_episodes  # the first phase with updates
    done, todo = t.phases.updates(episode)
    assert done == 0 and todo == round(cfg.algo.td.updates_per_step * cfg.env.episode_steps)
    t.phases.updates = lambda e: (0, 2)  # two critic steps (and one TD3 actor step)
    t.phases.run(transitions(2, 300), 16, totals, episode)
    online, target = t.loss.qvalue_network_params, t.loss.target_qvalue_network_params
    assert not torch.equal(before["module", "net", "layers", "0", "weight"],
                           target["module", "net", "layers", "0", "weight"])
    # After the last soft update: target = 0.75 target_before_it + 0.25 online, so it lies strictly
    # between; check one step explicitly by repeating it.
    saved = target.clone()
    t.phases.updater.step()
    for key in saved.keys(True, True):
        expected = saved[key] * 0.75 + online[key].detach() * 0.25
        torch.testing.assert_close(target[key], expected)
    means = totals.means(2)
    assert {"critic/loss_qvalue", "actor/loss_actor"} <= set(means[0])


def test_the_update_schedule_counts_gradient_steps_per_environment_step():
    td = load("algo=sac").algo.td
    assert td.warmup_episodes == 5 and td.updates_before(4, 200) == 0
    per_episode = round(td.updates_per_step * 200)
    assert td.updates_before(5, 200) == per_episode and td.updates_before(9, 200) == 5 * per_episode
    odd = load("algo=sac", "algo.td.updates_per_step=0.013", "algo.td.warmup_episodes=0").algo.td
    assert [odd.updates_before(e, 200) for e in range(5)] == [0, 2, 5, 7, 10]  # fractions carry over


# ------------------------------------------------------------------- prioritised replay
def test_sampling_frequencies_follow_priority_to_the_alpha():
    sampler = ProportionalSampler(8, alpha=0.7, beta=0.5, eps=1e-6)
    sampler.extend(torch.arange(6))
    priorities = torch.tensor([0.1, 1.0, 2.0, 4.0, 0.5, 3.0])
    sampler.update_priority(torch.arange(6), priorities)
    generator = torch.Generator().manual_seed(0)
    index, weight = sampler.sample_members(6, 200_000, [generator])
    expected = (priorities.double() + 1e-6) ** 0.7
    expected /= expected.sum()
    observed = torch.bincount(index[0], minlength=6).double() / index.numel()
    torch.testing.assert_close(observed, expected, atol=3e-3, rtol=0)
    # weights: (N P(i))^-beta / max_j (N P(j))^-beta = (P(i) / min P)^-beta
    torch.testing.assert_close(weight[0], (expected[index[0]] / expected.min()) ** -0.5)
    assert weight.max() <= 1 and torch.isclose(weight.max(), torch.tensor(1.0, dtype=torch.float64))


def test_new_transitions_get_the_largest_priority_and_state_round_trips():
    sampler = ProportionalSampler(5, alpha=1.0, beta=1.0, eps=1e-6, members=2)
    sampler.extend(torch.arange(3))
    sampler.update_priority(torch.tensor([[0, 1], [2, 2]]), torch.tensor([[5.0, 0.0], [0.5, 2.0]]))
    sampler.extend(torch.tensor([3]))  # member 0's largest so far: 5; member 1's: 2 (the last write)
    torch.testing.assert_close(sampler._powered[3], torch.tensor([5.0, 2.0], dtype=torch.float64) + 1e-6)
    restored = ProportionalSampler(5, alpha=1.0, beta=1.0, eps=1e-6, members=2)
    restored.load_state_dict(sampler.state_dict())
    g1, g2 = torch.Generator().manual_seed(4), torch.Generator().manual_seed(4)
    assert all(torch.equal(x, y) for x, y in zip(sampler.sample_members(4, 50, [g1, g1]),
                                                 restored.sample_members(4, 50, [g2, g2])))
    with pytest.raises(ValueError, match="finite and non-negative"):
        sampler.update_priority(torch.tensor([[0], [0]]), torch.tensor([[float("nan")], [1.0]]))
    with pytest.raises(ValueError, match="saved priorities have shape"):
        ProportionalSampler(7, 1.0, 1.0, members=2).load_state_dict(sampler.state_dict())


def test_the_sampler_plugs_into_a_torchrl_replay_buffer():
    sampler = ProportionalSampler(100, alpha=1.0, beta=0.4, generator=torch.Generator().manual_seed(0))
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(100), sampler=sampler, batch_size=64)
    buffer.extend(TensorDict({"x": torch.arange(10.0)}, batch_size=[10]))
    sampler.update_priority(torch.arange(10), torch.tensor([0.0] * 9 + [1000.0]))
    batch = buffer.sample()
    assert WEIGHT_KEY in batch.keys() and batch["x"].eq(9).float().mean() > 0.9
    assert batch[WEIGHT_KEY][batch["x"] == 9].max() < 1e-3  # the over-sampled one is down-weighted


# --------------------------------------------------------------------------- configs
@pytest.mark.parametrize("override, message", [
    (["algo=sac", "er=recent"], "trains off-policy on a replay memory"),
    (["algo=td3", "er=hybrid"], "trains off-policy on a replay memory"),
    (["er=prioritised", "er.train_on_recent=true"], "priority samples the replay memory"),
    (["algo=sac", "+algo.value_epochs=3"], "belong to the paper's protocol"),
    (["algo=td3", "algo.td3.policy_delay=0"], "policy_delay must be >= 1"),
    (["algo=td3", "algo.td3.preact_penalty=-0.1"], "preact_penalty must be >= 0"),
    (["algo=tqc", "algo.tqc.drop_per_critic=25"], "the target would keep no quantile"),
    (["algo=tqc", "algo.td.loss_function=l2"], "quantile Huber loss"),
    (["algo=crossq", "algo.td.tau=0.005"], "crossq has no target networks"),
    (["algo=sac", "algo.td.tau=null"], "updates target networks by algo.td.tau"),
    (["algo=crossq", "er=prioritised"], "does not weight by priority"),
    (["algo=crossq", "compile=true"], "not supported for crossq"),
    (["algo=sac", "algo.td.tau=0"], "tau must be in (0, 1]"),
    (["algo=td3", "algo.td.pessimism=0"], "algo.td.pessimism is built for the losses sac"),
    (["algo=sac", "algo.td.pessimism=100"], "must be within [-10, 10] standard deviations"),
    (["algo=sac", "er=prioritised", "er.priority.beta=2"], "beta must be in [0, 1]"),
])
def test_bad_offpolicy_settings_are_refused_with_a_reason(override, message):
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")
                       .replace("]", r"\]")):
        load(*override)


# ------------------------------------------------------------------------ whole runs
@pytest.mark.slow
@pytest.mark.parametrize("algo, er", [("td3", "prioritised"), ("redq", "memory")])  # SAC through train.py: tests/test_readme.py
def test_train_py_trains_two_episodes(tmp_path, algo, er):
    result = run_train(f"algo={algo}", f"er={er}", "seed=3", "episodes=2", "algo.td.warmup_episodes=1",
                       "algo.td.updates_per_step=0.05", "progress=false", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["algo"] == algo and summary["status"] == "completed" and summary["episodes"] == 2
    rows = read_rows(tmp_path / "metrics.csv")
    assert rows[0]["critic/loss_qvalue"] == "" and float(rows[1]["critic/loss_qvalue"]) > 0  # warm-up, then updates
    assert {"actor", "critic"} <= {p.stem for p in tmp_path.glob("*.pt")}


@pytest.mark.slow
@pytest.mark.parametrize("algo, er", [("sac", "prioritised"), ("crossq", "memory"), ("td3", "memory"),
                                     ("simbav2", "prioritised")])
def test_an_interrupted_population_resumes_exactly(tmp_path, algo, er):
    run = [f"algo={algo}", f"er={er}", *FAST, "episodes=5", "checkpoint_every=2", f"seeds=[{A},{B}]"]
    train_population(load(*run), tmp_path / "reference")
    with interrupted_after(3):
        train_population(load(*run), tmp_path / "run")
    summaries = train_population(load(*run), tmp_path / "run")
    assert [s["resumed_at"] for s in summaries] == [2, 2]
    for seed in (A, B):
        assert ((tmp_path / "run" / f"seed{seed}" / "metrics.csv").read_bytes()
                == (tmp_path / "reference" / f"seed{seed}" / "metrics.csv").read_bytes())


@pytest.mark.parametrize("algo, er", [pytest.param("sac", "memory", marks=pytest.mark.slow),
                                     pytest.param("tqc", "prioritised", marks=pytest.mark.slow),
                                     pytest.param("crossq", "memory", marks=pytest.mark.slow), ("td3", "prioritised"),
                                     pytest.param("simbav2", "prioritised", marks=pytest.mark.slow)])
def test_each_member_equals_its_solo_run(tmp_path, algo, er):
    """Every draw (minibatches, priorities, the losses' noise) comes from the member's own generator;
    the run's deterministic policy loads for evaluation."""
    run = [f"algo={algo}", f"er={er}", *FAST, "algo.td.updates_per_step=0.1"]
    train_population(load(*run, f"seed={B}"), tmp_path / "solo")
    train_population(load(*run, f"seeds=[{B},{A}]"), tmp_path / "pair")
    assert ((tmp_path / "pair" / f"seed{B}" / "metrics.csv").read_bytes()
            == (tmp_path / "solo" / "metrics.csv").read_bytes())
    cfg = load(*run)
    policy = make_policy(algo, {"actor_hidden": cfg.network.actor_hidden, "activation": cfg.network.activation}, 6,
                         torch.load(tmp_path / "solo" / "actor.pt"), algo=cfg.algo)
    assert policy(np.zeros(6)).shape == (2,)


def test_a_diverging_sac_member_is_frozen_and_the_other_finishes(tmp_path, monkeypatch):
    from learners.td.learner import TDPhaseRunner

    original, calls = TDPhaseRunner.run, []

    def poisoned(self, *args):
        calls.append(1)
        if len(calls) == 2:
            with torch.no_grad():
                self.optimisers.critic.params[0][:, 0].fill_(float("nan"))
        return original(self, *args)

    monkeypatch.setattr(TDPhaseRunner, "run", poisoned)
    summaries = train_population(load("algo=sac", "er=memory", *FAST, f"seeds=[{A},{B}]"), tmp_path)
    assert [s["status"] for s in summaries] == ["diverged", "completed"]
    assert "critic" in summaries[0]["diverged"]["reason"] or "loss" in summaries[0]["diverged"]["reason"]
    assert len(read_rows(tmp_path / f"seed{B}" / "metrics.csv")) == 4


@pytest.mark.slow
def test_a_population_evaluates_itself_and_evaluate_py_tables_a_sweep(tmp_path, capsys):
    """eval_seeds: each member's summary holds its deterministic policy's scores; evaluate.py on
    the population's folder evaluates every member (SAC's actor rebuilt from actor.pt)."""
    import evaluate

    result = run_train("algo=sac", f"seeds=[{A},{B}]", *FAST[1:], "episodes=2", "eval_seeds=[11,12]",
                       "eval_episodes=1", f"hydra.run.dir={tmp_path / 'pop'}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "pop" / f"seed{A}" / "summary.json").read_text())
    evaluation = summary["evaluation"]
    assert set(evaluation["tracks"]) == {"11", "12"} and evaluation["episodes"] == 1
    assert evaluation["mean"] == pytest.approx(sum(evaluation["tracks"].values()) / 2)
    table = tmp_path / "evaluation.csv"
    assert evaluate.main([str(tmp_path / "pop"), "--tracks", "11", "--episodes", "1", "--table", str(table)]) == 0
    rows = read_rows(table)
    assert len(rows) == 4 and {r["algo"] for r in rows} == {"sac"}
    own = {int(r["train_seed"]): float(r["mean_reward"]) for r in rows if r["own_track"] == "True"}
    assert own[A] == pytest.approx(evaluation["own_track"], abs=1e-5)  # the same policy, episodes and start states
    assert "| run | own track |" in capsys.readouterr().out
    # actor.pt in the layout of TorchRL's parameters, as the first SAC/TD3 runs saved it, loads too
    folder = tmp_path / "pop" / f"seed{A}"
    policy, _ = load_policy(folder)
    state = torch.load(folder / "actor.pt", weights_only=True)
    torch.save({f"module.{k}": v for k, v in state.items()}, folder / "actor.pt")
    summary = json.loads((folder / "summary.json").read_text())
    del summary["files"], summary["sha256"]  # nor did those runs' summaries record their files, nor a digest
    summary["code"]["commit"] = "9683e1933be8ab1224c9af2cce4fe5dbb339a2cb"  # a commit of theirs
    (folder / "summary.json").write_text(json.dumps(summary))
    older, _ = load_policy(folder)
    observation = np.linspace(0.0, 1.0, 6, dtype=np.float32)
    np.testing.assert_array_equal(older(observation), policy(observation))


@pytest.mark.slow
def test_the_generalisation_preset_shares_its_fixed_runs_with_beyond_paper_and_reports(tmp_path):
    """+experiment=generalisation (6 cells x fixed/random tracks), then +experiment=beyond_paper in
    the same folder skips the fixed-track runs already made; report.py writes both tables."""
    import report

    tiny = ["episodes=1", f"seeds=[{A}]", "eval_seeds=[11]", "eval_episodes=1", "hydra/launcher=basic",
            f"hydra.sweep.dir={tmp_path}"]
    result = run_train("-m", "+experiment=generalisation", *tiny)
    assert result.returncode == 0, result.stderr[-3000:]
    made = sorted(p.parent.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("summary.json"))
    assert len(made) == 12 and f"random/sac/memory/seed{A}" in made and f"fixed/crossq/memory/seed{A}" in made
    result = run_train("-m", "+experiment=beyond_paper", *tiny)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.count("skipped") + result.stderr.count("skipped") == 6
    assert len(list(tmp_path.rglob("summary.json"))) == 12 + 4
    assert report.main([str(tmp_path), "--no-figures"]) == 0
    assert "| SAC, prioritised |" in (tmp_path / "report" / "beyond.md").read_text()
    assert "| TD3, memory | random | 1 |" in (tmp_path / "report" / "generalisation.md").read_text()


@pytest.mark.slow
def test_spg_p_with_prioritised_replay_weights_its_critic_and_updates_priorities(tmp_path):
    """The paper's conjecture, testable: SPG-p on a prioritised memory. Priorities move away from
    their initial value, and a run is reproducible and resumable like any other."""
    from engine.setup import make_learner as build

    cfg = load("algo=spg_p", "er=prioritised", f"seeds=[{A},{B}]")
    t = build(cfg, make_env(cfg, (A, B)), make_generators((A, B)))
    assert t.phases.sampler is t.memory.sampler is not None
    run = ["algo=spg_p", "er=prioritised", "episodes=3", "progress=false", "logger=none", f"seeds=[{A},{B}]"]
    first = train_population(load(*run), tmp_path / "a")
    second = train_population(load(*run), tmp_path / "b")
    assert [s["final_mean"] for s in first] == [s["final_mean"] for s in second]
    uniform = train_population(load(*run[:1], "er=memory", *run[2:]), tmp_path / "c")
    assert [s["final_mean"] for s in uniform] != [s["final_mean"] for s in first]


def test_the_critic_loss_is_importance_weighted_and_reports_errors():
    from losses.common import PRIORITY_KEY, PRIORITY_WEIGHT_KEY

    cfg = load("algo=spg_p", "er=prioritised", f"seeds=[{A},{B}]")
    t = make_learner(cfg, make_env(cfg, (A, B)), make_generators((A, B)))
    data = transitions(2, 8)
    data["value_target"] = torch.rand(2, 8, 1)
    plain = t.loss.critic_loss(data.clone())
    assert PRIORITY_KEY not in plain.keys()
    weights = torch.rand(2, 8)
    data[PRIORITY_WEIGHT_KEY] = weights
    weighted = t.loss.critic_loss(data)
    value = t.loss._value(data)
    error = (data["value_target"] - value).squeeze(-1)
    torch.testing.assert_close(weighted["loss_critic"], (weights * error ** 2).mean(-1))
    torch.testing.assert_close(weighted[PRIORITY_KEY], error.abs().detach())
    torch.testing.assert_close(plain["loss_critic"], (error ** 2).mean(-1))


def test_every_off_policy_learner_declares_its_step():
    """Each learner the td family trains declares what the machinery asks of it (learners.registry)."""
    from learners.registry import LEARNERS

    for name, spec in LEARNERS.items():
        if spec.family != "td":
            continue
        steps = spec.torch_half()
        for part in ("METRICS", "actor", "critics", "exploration_noise", "loss", "prepare"):
            assert hasattr(steps, part), (name, part)
        assert hasattr(steps, "step") or hasattr(steps, "phase"), name
