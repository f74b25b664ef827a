"""NAF (losses/naf.py): the advantage and its Cholesky parametrisation, the TD targets, the loss's
gradients against hand-derived ones, and the learner in the population pipeline."""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.objectives import SoftUpdate

from engine.evaluation import make_policy
from engine.runner import train_population
from learners.td import naf
from learners.base import MetricTotals
from losses.naf import NAFLoss, lower_entries, naf_advantage, naf_lower, naf_precision
from tests.test_config import load
from tests.test_offpolicy import A, B, FAST, training, transitions
from tests.test_resilience import interrupted_after


# ------------------------------------------------------------------------- the advantage
def test_the_lower_factor_and_the_advantage_are_the_hand_computed_ones():
    # entries (0.1, 0.5, -0.2) row by row: L = [[e^0.1, 0], [0.5, e^-0.2]]
    entries = torch.tensor([0.1, 0.5, -0.2], dtype=torch.float64)
    expected = torch.tensor([[math.exp(0.1), 0.0], [0.5, math.exp(-0.2)]], dtype=torch.float64)
    torch.testing.assert_close(naf_lower(entries, 2), expected, rtol=0, atol=0)
    mu, action = torch.tensor([0.2, -0.3], dtype=torch.float64), torch.tensor([0.5, 0.1], dtype=torch.float64)
    d0, d1 = 0.3, 0.4  # action - mu
    # L^T d = (e^0.1 d0 + 0.5 d1, e^-0.2 d1); A = -1/2 |L^T d|^2
    hand = -0.5 * ((math.exp(0.1) * d0 + 0.5 * d1) ** 2 + (math.exp(-0.2) * d1) ** 2)
    assert naf_advantage(entries, mu, action).item() == pytest.approx(hand, rel=1e-14)
    assert lower_entries(2) == 3 and lower_entries(3) == 6


def test_the_advantage_is_a_negative_quadratic_form_of_a_positive_definite_matrix_peaking_at_mu():
    g = torch.Generator().manual_seed(0)
    entries = torch.randn(64, lower_entries(3), generator=g, dtype=torch.float64) * 2
    mu = torch.rand(64, 3, generator=g, dtype=torch.float64) * 2 - 1
    action = torch.rand(64, 3, generator=g, dtype=torch.float64) * 2 - 1
    precision = naf_precision(entries, 3)
    torch.testing.assert_close(precision, precision.transpose(-1, -2), rtol=0, atol=1e-12)
    assert torch.linalg.eigvalsh(precision).min() > 0
    lower = naf_lower(entries, 3)
    assert torch.equal(lower, lower.tril()) and lower.diagonal(dim1=-2, dim2=-1).gt(0).all()
    d = (action - mu).unsqueeze(-1)
    reference = -0.5 * (d.transpose(-1, -2) @ precision @ d).reshape(64)
    torch.testing.assert_close(naf_advantage(entries, mu, action), reference, rtol=1e-12, atol=1e-12)
    assert naf_advantage(entries, mu, mu).abs().max() == 0  # the greedy action is mu
    assert naf_advantage(entries, mu, action).lt(0).all()


# ---------------------------------------------------------------------------- the loss
class _Linear(nn.Module):
    def __init__(self, inputs, outputs, seed):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.weight = nn.Parameter(torch.randn(outputs, inputs, generator=g, dtype=torch.float64) * 0.3)
        self.bias = nn.Parameter(torch.randn(outputs, generator=g, dtype=torch.float64) * 0.3)

    def forward(self, x):
        return x @ self.weight.T + self.bias


def _naf_loss(gamma=0.9, **kwargs):
    actor = TensorDictModule(_Linear(6, 2, 1), ["observation"], ["action"])
    value = TensorDictModule(_Linear(6, 4, 2), ["observation"], ["naf"])
    loss = NAFLoss(actor, value, 2, **kwargs)
    loss.make_value_estimator(gamma=gamma)
    SoftUpdate(loss, tau=0.005)  # the target network's updater, as a user of TorchRL's losses pairs one
    return loss


def _batch(n=5, seed=0):
    data = transitions(1, n, seed)[0].apply(lambda t: t.double() if t.is_floating_point() else t)
    data.set(("next", "terminated"), torch.tensor([[False], [True], [False], [False], [True]])[:n])
    return data


def test_the_target_is_reward_plus_discounted_target_value_except_at_termination_and_n_steps_discount_further():
    loss = _naf_loss(gamma=0.9)
    data = _batch()
    with torch.no_grad():  # perturb the online value network: the target reads the target copy
        loss.value_network.module.bias.add_(1.0)
    target_v = data["next", "observation"] @ loss.target_value_network_params["module", "weight"][0] \
        + loss.target_value_network_params["module", "bias"][0]
    reward, terminated = data["next", "reward"][:, 0], data["next", "terminated"][:, 0]
    gamma = float(torch.tensor(0.9, dtype=torch.float32))  # TorchRL's estimators hold gamma in float32
    hand = reward + gamma * target_v * (~terminated)
    torch.testing.assert_close(loss.target(data), hand, rtol=1e-14, atol=1e-14)
    data.set("steps_to_next_obs", torch.tensor([[1], [2], [3], [1], [2]]))
    steps = torch.tensor([1, 2, 3, 1, 2])
    hand = reward + (torch.tensor(0.9, dtype=torch.float32) ** steps).double() * target_v * (~terminated)
    torch.testing.assert_close(loss.target(data), hand, rtol=1e-14, atol=1e-14)


def test_the_loss_its_priorities_and_its_gradients_are_the_hand_derived_ones():
    loss = _naf_loss(gamma=0.9, reduction="mean")
    data = _batch()
    n = data.shape[0]
    out = loss(data)
    actor, value = loss.actor_network.module, loss.value_network.module
    with torch.no_grad():
        s, a = data["observation"], data["action"]
        mu, v_out = actor(s), value(s)
        e0, e1, e2 = v_out[:, 1], v_out[:, 2], v_out[:, 3]
        l00, l10, l11 = e0.exp(), e1, e2.exp()
        d0, d1 = a[:, 0] - mu[:, 0], a[:, 1] - mu[:, 1]
        u0, u1 = l00 * d0 + l10 * d1, l11 * d1  # L^T d
        q = v_out[:, 0] - 0.5 * (u0 ** 2 + u1 ** 2)
        y = loss.target(data)
        assert out["loss_qvalue"].item() == pytest.approx(((q - y) ** 2).mean().item(), rel=1e-13)
        torch.testing.assert_close(data["td_error"], (q - y).abs(), rtol=1e-13, atol=1e-13)
        # d loss / d outputs, per transition (mean over n): dQ/dV = 1; dA/de0 = -u0 * l00 * d0,
        # dA/de1 = -u0 * d1, dA/de2 = -u1 * l11 * d1; dA/dmu = P d = L (L^T d) = (l00 u0, l10 u0 + l11 u1)
        c = 2 * (q - y) / n
        d_out = torch.stack([c, c * -u0 * l00 * d0, c * -u0 * d1, c * -u1 * l11 * d1], -1)
        d_mu = torch.stack([c * l00 * u0, c * (l10 * u0 + l11 * u1)], -1)
    out["loss_qvalue"].backward()
    torch.testing.assert_close(value.bias.grad, d_out.sum(0), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(value.weight.grad, d_out.T @ s, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(actor.bias.grad, d_mu.sum(0), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(actor.weight.grad, d_mu.T @ s, rtol=1e-12, atol=1e-14)
    assert loss.target_value_network_params["module", "bias"].grad is None  # the target takes no gradient


def test_importance_weights_scale_each_transitions_loss_and_bad_reductions_are_refused():
    loss = _naf_loss()
    data = _batch()
    plain = loss(data.clone())["loss_qvalue"].detach()
    weighted = data.clone()
    weighted.set("priority_weight", torch.tensor([0.5, 1.0, 2.0, 0.0, 1.5], dtype=torch.float64))
    torch.testing.assert_close(loss(weighted)["loss_qvalue"].detach(), plain * weighted["priority_weight"])
    with pytest.raises(ValueError, match="reduction must be"):
        _naf_loss(reduction="sum")
    with pytest.raises(NotImplementedError, match="TD\\(0\\)"):
        loss.make_value_estimator("gae", gamma=0.9)


# ------------------------------------------------------------------------- the learner
def test_naf_trains_mu_and_the_value_network_by_one_loss_and_members_do_not_mix():
    cfg, t = training("naf")
    data = transitions(2, 32)
    params = t.optimisers.actor.params + t.optimisers.critic.params

    def grads(batch):
        for p in params:
            p.grad = None
        t.loss(batch.clone())["loss_qvalue"].mean(-1).sum().backward()
        return [p.grad.clone() for p in params]

    first = grads(data)
    assert all(g.any() for g in first)  # every parameter of mu, V and L
    other = data.clone()
    other[1] = transitions(2, 32, seed=9)[1]
    for g0, g1 in zip(first, grads(other)):  # [member, ...]: member 0's unchanged
        torch.testing.assert_close(g0[0], g1[0], rtol=0, atol=0)
        assert not torch.equal(g0[1], g1[1])


def test_naf_target_network_follows_by_tau_and_a_frozen_member_stays_zero():
    cfg, t = training("naf", "algo.td.tau=0.25")
    target, online = t.loss.target_value_network_params, t.loss.value_network_params
    t.phases.updates = lambda e: (0, 2)
    totals = MetricTotals()
    t.phases.run(transitions(2, 300), 16, totals, cfg.algo.td.warmup_episodes)
    saved = target.clone()
    t.phases.updater.step()
    for key in saved.keys(True, True):
        torch.testing.assert_close(target[key], saved[key] * 0.75 + online[key].detach() * 0.25)
    assert {"critic/loss_qvalue", "critic/value", "critic/advantage"} == set(totals.means(2)[0])
    t.phases.freeze(1)
    assert all(not p[1].any() for p in target.values(True, True))
    t.phases.run(transitions(2, 300), 16, totals, cfg.algo.td.warmup_episodes)
    assert all(not p[1].any() for p in online.values(True, True)) and all(p[0].any() for p in online.values(True, True))
    critic = t.phases.member_critic(0)
    assert critic["module.net.layers.0.weight"].shape == online["module", "net", "layers", "0", "weight"].shape[1:]


@pytest.mark.slow
def test_a_naf_member_equals_its_solo_run_resumes_exactly_and_its_policy_loads(tmp_path):
    run = ["algo=naf", "er=prioritised", *FAST, "algo.td.updates_per_step=0.1", "episodes=5", "checkpoint_every=2"]
    train_population(load(*run, f"seed={B}"), tmp_path / "solo")
    with interrupted_after(3):
        train_population(load(*run, f"seeds=[{B},{A}]"), tmp_path / "pair")
    summaries = train_population(load(*run, f"seeds=[{B},{A}]"), tmp_path / "pair")
    assert [s["resumed_at"] for s in summaries] == [2, 2]
    assert ((tmp_path / "pair" / f"seed{B}" / "metrics.csv").read_bytes()
            == (tmp_path / "solo" / "metrics.csv").read_bytes())
    cfg = load(*run)
    policy = make_policy("naf", {"actor_hidden": cfg.network.actor_hidden, "activation": cfg.network.activation}, 6,
                         torch.load(tmp_path / "solo" / "actor.pt"))
    action = policy(np.zeros(6))
    assert action.shape == (2,) and np.abs(action).max() <= 1


@pytest.mark.parametrize("override, message", [
    (["algo.td.critic_dropout=0.1"], "value network .* is a plain MLP"),
    (["algo.naf.exploration_noise=-0.1"], "algo.naf.exploration_noise must be"),
    (["algo.td.tau=null"], "updates target networks"),
    (["er=hybrid"], "replay memory"),
    (["algo.td.updates_per_step=1e12"], "above its ceiling"),
    (["algo.td.critic_weight_decay=4000"], "must be below 1"),
    (["algo.naf.preact_penalty=1e39"], "float32"),
    (["algo.td.n_step=300"], "longer than an episode"),
    (["env.options.crash_penalty=1e39"], "float32 reward"),
])
def test_bad_naf_settings_are_refused_with_a_reason(override, message):
    from engine.config import ConfigError

    with pytest.raises(ConfigError, match=message):
        load("algo=naf", *override)


def test_the_pre_tanh_penalty_adds_its_mean_square_to_mus_objective_only():
    cfg, t = training("naf", "algo.naf.preact_penalty=0.5")
    data = transitions(2, 32)
    losses, _, penalty = naf.losses(t.phases, data.clone())
    body = t.networks.actor_net[0]
    expected = 0.5 * body(data["observation"]).square().reshape(2, -1).mean(-1)
    torch.testing.assert_close(penalty, expected, rtol=0, atol=0)
    critic = t.optimisers.critic.params
    for p in critic:
        p.grad = None
    penalty.sum().backward()
    assert all(p.grad is None or not p.grad.any() for p in critic)
    _, _, none = naf.losses(training("naf", "algo.naf.preact_penalty=0")[1].phases, data.clone())
    assert not none.any()


@pytest.mark.slow
def test_analysis_naf_reads_the_advantages_curvature_along_the_runs_own_track(tmp_path, capsys):
    """``python -m analysis.naf`` (docs/results.md's diagnosis of NAF) on a train.py run and a population."""
    from analysis.naf import curvature, main
    from tests.test_train import run_train

    result = run_train("algo=naf", "seeds=[3,4]", "episodes=3", "algo.td.warmup_episodes=1",
                       "algo.td.updates_per_step=0.05", "progress=false", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-2000:]
    figures = curvature(tmp_path / "seed3")
    assert figures["trace_median"] > 0 and figures["initial_median"] > 0 and -1 <= figures["throttle"] <= 1
    assert main([str(tmp_path)]) == 0  # a population's folder: each member
    assert capsys.readouterr().out.count("| " + str(tmp_path)) == 2
    from engine.evaluation import RunFolderError, load_policy

    with pytest.raises(RunFolderError, match=r"a population's folder, not a run: give one of its members' folders "
                                             r"\(seed3, seed4\)"):
        load_policy(tmp_path)  # evaluate.py and score.py read a run through it
