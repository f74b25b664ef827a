"""The paper's learners' fused steps (``learners.monte_carlo.fused``) against their loss modules.

A fused step is only a faster way to compute what the loss module computes: every phase below is
run twice from the same state, through ``SPGLoss``/``LogClipPPOLoss`` and fused, and every
parameter, Adam moment, diagnostic and generator must come out bit for bit the same.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from engine.setup import make_env, make_generators, make_learner
from learners.base import MetricTotals
from learners.monte_carlo import learner as mc
from tests.test_config import load

SEEDS = (2067791, 5468063, 773203)


def _learner(*overrides: str, seeds=SEEDS):
    cfg = load(*overrides, f"seeds=[{','.join(map(str, seeds))}]")
    generators = make_generators(tuple(seeds))
    return make_learner(cfg, make_env(cfg, tuple(seeds)), generators), generators


def _phase_data(members: int, n: int, obs_dim: int, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({"observation": torch.rand(members, n, obs_dim, generator=g) * 2 - 0.5,
                       "action": torch.rand(members, n, 2, generator=g) * 2 - 1,
                       "value_target": torch.randn(members, n, 1, generator=g) * 30 + 50},
                      batch_size=[members, n])


def _state(t, generators, totals: MetricTotals) -> list[torch.Tensor]:
    optimisers = t.optimisers
    return [*optimisers.actor.params, *optimisers.critic.params, *optimisers.actor.exp_avg,
            *optimisers.actor.exp_avg_sq, *optimisers.critic.exp_avg, *optimisers.critic.exp_avg_sq,
            *[g.get_state() for g in generators], *[torch.stack(v) for v in totals.values.values()],
            *[b for b in t.loss.buffers()]]


def _phases(fused: bool, overrides, minibatch: int, phases: int = 3, freeze: int | None = None):
    t, generators = _learner(*overrides)
    assert t.phases.fused_critic is not None  # these configurations allow it
    assert t.phases.fused_actor is not None
    if not fused:
        t.phases.fused_critic = t.phases.fused_actor = None
    if freeze is not None:
        t.phases.freeze(freeze)
    obs_dim = t.networks.actor_net.body.layers[0].weight.shape[-1]
    totals = MetricTotals()
    for k in range(phases):
        data = _phase_data(len(generators), 150 + 7 * k, obs_dim, seed=k)
        assert t.phases.run(data, minibatch, totals) == {}
    if "algo.actor_lr=0.01" in overrides:  # the ratio leaves its clip bounds: both branches of the surrogate
        clipped = torch.stack(totals.values["actor/clip_fraction"])
        assert clipped.gt(0).any() and clipped.lt(1).all()
    return _state(t, generators, totals), list(totals.values)


@pytest.mark.parametrize("overrides", [["algo=spg_p_multi"], ["algo=spg"], ["algo=ppo"], ["algo=ppo_log"],
                                       ["algo=spg_multi", "env.past_steps=2", "algo.value_epochs=7"],
                                       ["algo=ppo", "network.critic_hidden=[24,40,16]", "network.actor_hidden=[48,40]"],
                                       ["algo=ppo_log", "algo.joint_log_prob=true"],
                                       ["algo=spg_p", "algo.joint_log_prob=true", "algo.spg.baseline=action",
                                        "algo.spg.sample_around=action"],
                                       ["algo=ppo", "algo.entropy_coeff=0"],
                                       ["algo=ppo", "algo.actor_lr=0.01"], ["algo=ppo_log", "algo.actor_lr=0.01"]])
@pytest.mark.parametrize("minibatch", [100, 37])
def test_a_fused_phase_is_the_loss_modules_phase_bit_for_bit(overrides, minibatch):
    """Three phases of three members on data of different sizes: the same parameters, Adam moments,
    per-step diagnostics, generator states and temperatures (SPG), whether the minibatch fills its
    padded rows (100 of 104) or not (37 of 40), with deeper networks of other widths, a wider
    observation (env.past_steps), joint log-probabilities, SPG's other centre and baseline, PPO with and
    without its entropy bonus and with ratios outside the clip bounds."""
    theirs, names = _phases(False, overrides, minibatch)
    ours, our_names = _phases(True, overrides, minibatch)
    assert names == our_names and len(ours) == len(theirs)
    for a, b in zip(theirs, ours, strict=True):
        assert a.dtype == b.dtype and torch.equal(a, b)


def test_a_frozen_member_stays_frozen_and_the_others_train_as_before():
    theirs, _ = _phases(False, ["algo=spg_p_multi"], 100, phases=2, freeze=1)
    ours, _ = _phases(True, ["algo=spg_p_multi"], 100, phases=2, freeze=1)
    assert all(torch.equal(a, b) for a, b in zip(theirs, ours, strict=True))
    t, _ = _learner("algo=spg_p_multi")
    critic = t.optimisers.critic.params
    assert all(not p[1].any() for p in ours[len(t.optimisers.actor.params):][:len(critic)])


@pytest.mark.parametrize("overrides", [["algo=spg", "er=prioritised"], ["algo=ppo", "network.activation=relu"],
                                       ["algo=spg", "compile=true"], ["algo=ppo", "numerics=portable"]])
def test_the_loss_module_takes_every_step_the_fused_one_does_not_compute(overrides, monkeypatch):
    """Prioritised replay (importance weights, new priorities), another activation, compiled steps and
    other products stay on the loss module's path (the reference)."""
    from learners import kernels

    previous = kernels.active()
    try:
        if "numerics=portable" in overrides:
            kernels.use(False)
        t, _ = _learner(*overrides)
        assert t.phases.fused_critic is None
    finally:
        kernels.use(previous)
    monkeypatch.setattr(mc, "FUSED", False)
    assert _learner("algo=spg")[0].phases.fused_critic is None


@pytest.mark.parametrize("change", ["public setting", "private setting", "parameter", "submodule", "subclass",
                                    "method on the instance", "method on the class"])
def test_a_loss_the_fused_steps_do_not_know_takes_the_loss_modules_path(change, monkeypatch):
    """A setting added to a loss module (public or not), a parameter, a submodule, a subclass or another
    method: the loss module computes, the fused steps never ignore what they do not know."""
    from learners.monte_carlo.fused import loss_known
    from losses import SPGLoss

    t, _ = _learner("algo=spg")
    assert loss_known(t.loss)
    loss = t.loss
    if change == "public setting":
        loss.clip_weights = True
    elif change == "private setting":
        loss._clip_weights = 5.0
    elif change == "parameter":
        loss.register_parameter("log_alpha", torch.nn.Parameter(torch.zeros(3)))
    elif change == "submodule":
        loss.add_module("extra", torch.nn.Linear(2, 2))
    elif change == "subclass":
        loss.__class__ = type("MySPGLoss", (SPGLoss,), {})
    elif change == "method on the instance":
        loss.actor_loss = lambda td: SPGLoss.actor_loss(loss, td)
    else:
        original = SPGLoss.actor_loss

        def actor_loss(self, tensordict):  # another objective
            return original(self, tensordict)
        monkeypatch.setattr(SPGLoss, "actor_loss", actor_loss)
    assert not loss_known(loss)
    assert _learner("algo=spg")[0].phases.fused_actor is None if change == "method on the class" else True
