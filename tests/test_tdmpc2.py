"""algo=tdmpc2: the latent model's pieces (learners.latent), MPPI's update, the latent losses over a horizon with
episode ends inside it (losses.tdmpc2), each against hand-computed values; a member equals its solo run and
resumes exactly, its saved model loads as a policy; its configuration's refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from engine.config import ConfigError
from engine.evaluation import make_policy
from engine.runner import train_population
from learners import latent
from learners.latent import PlanOptions, plan, shifted, simnorm, split_draws
from losses.functional import symexp, symlog
from losses.tdmpc2 import Support
from losses.tdmpc2 import PRIOR_NOISE_KEY, TARGET_NOISE_KEY, cross_entropy, two_hot
from tests.test_config import load
from tests.test_offpolicy import A, training, solo_and_resumed_pair

# episodes of 40 steps keep the planner's runs short
SHORT = ["er=memory", "env.options.max_steps=40", "er.buffer_size=400", "algo.td.warmup_episodes=1",
         "algo.td.updates_per_step=0.25", "algo.minibatch_size=8", "progress=false", "logger=none"]


# ------------------------------------------------------------------ the model's pieces
def test_simnorm_makes_each_group_a_softmax():
    x = torch.randn(2, 3, 16, generator=torch.Generator().manual_seed(0))
    out = simnorm(x, 8)
    for group in (slice(0, 8), slice(8, 16)):
        e = x[..., group].exp()
        torch.testing.assert_close(out[..., group], e / e.sum(-1, keepdim=True))
    torch.testing.assert_close(out.reshape(2, 3, 2, 8).sum(-1), torch.ones(2, 3, 2))


def test_symlog_and_symexp_are_inverse_and_two_hot_splits_the_mass_between_the_points_around_it():
    x = torch.tensor([[-5.0], [-0.5], [0.0], [0.5], [5.0]])
    torch.testing.assert_close(symlog(x), x.sign() * torch.log(1 + x.abs()))
    torch.testing.assert_close(symexp(symlog(x)), x)
    support = Support(v_max=1.0, bins=3)  # points -1, 0, 1 in symlog units
    cases = [(math.expm1(0.3), [0.0, 0.7, 0.3]),  # symlog 0.3: 0.7 on 0, 0.3 on 1
             (-math.expm1(1.0), [1.0, 0.0, 0.0]),  # symlog -1: on the first point
             (1e6, [0.0, 0.0, 1.0]),  # beyond the support: clipped to its last point
             (-math.expm1(0.25), [0.25, 0.75, 0.0])]
    for value, expected in cases:
        torch.testing.assert_close(two_hot(torch.tensor([[value]]), support), torch.tensor([expected]))
    # the expected value of a two-hot distribution is the value itself
    inside = torch.tensor([[math.expm1(0.3)], [-math.expm1(0.25)]])
    torch.testing.assert_close(support.value(two_hot(inside, support).log()), inside)


def test_cross_entropy_by_hand():
    logits, target = torch.tensor([0.0, math.log(3.0)]), torch.tensor([0.5, 0.5])
    assert float(cross_entropy(logits, target)) == pytest.approx(-(0.5 * math.log(0.25) + 0.5 * math.log(0.75)))


# ------------------------------------------------------------------ MPPI
class _Prior:
    """A model whose prior is N(0, 1) squashed by tanh and whose dynamics keep the latent state."""

    group = 1

    def pi(self, z):
        return torch.zeros(*z.shape[:-1], 1), torch.ones(*z.shape[:-1], 1)

    def next(self, z, action):
        return z


def test_mppi_refits_the_plan_to_its_weighted_elites_and_acts_with_a_chosen_elite(monkeypatch):
    """Two members, one step ahead, three trajectories (one the prior's), two elites, one iteration, every value
    -(a - 0.3)^2: the plan's mean and standard deviation and the action computed by hand."""
    monkeypatch.setattr(latent, "trajectory_values",
                        lambda model, q, z, actions, terminal, support, gamma: -(actions[:, :, 0, 0] - 0.3) ** 2)
    options = PlanOptions(horizon=1, samples=3, policy_samples=1, elites=2, iterations=1, temperature=1.0,
                          min_std=0.05, max_std=1.0, gamma=0.9)
    assert options.draws_per_step(1) == 1 + 2 + 3 + 1
    # member 0: prior tanh(atanh 0.2) = 0.2, samples 0 + 1 x (0.6, -0.4); member 1: prior -0.9, samples 0.5 + (-0.2, 0.3)
    draws = torch.tensor([[math.atanh(0.2), 0.6, -0.4, 0.0, 0.0, 0.0, 0.5],
                          [math.atanh(-0.9), -0.2, 0.3, 0.0, 0.0, 0.0, -1.0]])
    mean = torch.tensor([[[0.0]], [[0.5]]])
    action, new_mean = plan(_Prior(), None, torch.zeros(2, 4), mean, split_draws(draws, options, 1),
                            torch.tensor([0.6, 0.1]), options, Support(1.0, 3))
    # member 0: values 0.2 -> -0.01, 0.6 -> -0.09, -0.4 -> -0.49; elites 0.2 and 0.6, weights 1 and e^-0.08
    w = math.exp(-0.08)
    mean0 = (0.2 + 0.6 * w) / (1 + w)
    std0 = math.sqrt(((0.2 - mean0) ** 2 + w * (0.6 - mean0) ** 2) / (1 + w))
    # member 1: values -0.9 -> -1.44, 0.3 -> 0, 0.8 -> -0.25; elites 0.3 and 0.8, weights 1 and e^-0.25
    v = math.exp(-0.25)
    mean1 = (0.3 + 0.8 * v) / (1 + v)
    std1 = math.sqrt(((0.3 - mean1) ** 2 + v * (0.8 - mean1) ** 2) / (1 + v))
    torch.testing.assert_close(new_mean, torch.tensor([[[mean0]], [[mean1]]]))
    # member 0's uniform 0.6 lies past the first elite's weight (0.52): the second elite, 0.6, plus std x 0.5;
    # member 1's 0.1 picks the first, 0.3, minus std
    torch.testing.assert_close(action, torch.tensor([[0.6 + std0 * 0.5], [0.3 - std1]]))
    without_prior = PlanOptions(horizon=1, samples=3, policy_samples=0, elites=2, iterations=1, temperature=1.0,
                                min_std=0.05, max_std=1.0, gamma=0.9)  # every trajectory the Gaussian's
    draws0 = torch.tensor([[0.2, 0.6, -0.4, 0.0, 0.0, 0.0, 0.5], [-0.2, 0.3, -0.9, 0.0, 0.0, 0.0, -1.0]])
    _, mean0_alone = plan(_Prior(), None, torch.zeros(2, 4), torch.zeros(2, 1, 1), split_draws(draws0, without_prior, 1),
                          torch.tensor([0.6, 0.1]), without_prior, Support(1.0, 3))
    torch.testing.assert_close(mean0_alone[0, 0, 0], torch.tensor(mean0))  # the same elites as above: 0.2 and 0.6
    noiseless, _ = plan(_Prior(), None, torch.zeros(2, 4), mean, split_draws(draws, options, 1),
                        torch.tensor([0.6, 0.1]), options, Support(1.0, 3), noisy=False)
    torch.testing.assert_close(noiseless, torch.tensor([[0.6], [0.3]]))


def test_the_warm_start_moves_the_plan_one_step_on():
    torch.testing.assert_close(shifted(torch.tensor([[[1.0], [2.0], [3.0]]])), torch.tensor([[[2.0], [3.0], [0.0]]]))


def test_a_trajectory_s_value_is_its_discounted_predicted_rewards_then_the_terminal_q():
    cfg, t = training("tdmpc2", "algo.tdmpc2.horizon=2", seeds=(A,))
    model, loss, support = t.networks.actor_net, t.loss, t.loss.support
    g = torch.Generator().manual_seed(3)
    z = model.encode(torch.rand(1, 4, 6, generator=g))
    actions, terminal = torch.rand(1, 4, 2, 2, generator=g) * 2 - 1, torch.randn(1, 4, 2, generator=g)
    with torch.no_grad():
        values = latent.trajectory_values(model, loss.planning_value, z, actions, terminal, support, 0.9)
        expected = []
        for n in range(4):  # one trajectory at a time
            state, total = z[:, n], 0.0
            for step in range(2):
                za = torch.cat([state, actions[:, n, step]], -1)
                total += 0.9 ** step * float(support.value(model.reward(za)))
                state = model.next(state, actions[:, n, step])
            loc, scale = model.pi(state)
            total += 0.9 ** 2 * float(loss.planning_value(state, torch.tanh(loc + scale * terminal[:, n])))
            expected.append(total)
    torch.testing.assert_close(values[0], torch.tensor(expected), rtol=1e-5, atol=1e-5)


# ------------------------------------------------------------------ the losses
def _sub_episodes(members, size, horizon, seed=0):
    g = torch.Generator().manual_seed(seed)
    shape = (members, size, horizon)
    return TensorDict({
        "observation": torch.rand(*shape, 6, generator=g), "action": torch.rand(*shape, 2, generator=g) * 2 - 1,
        "mask": torch.ones(*shape, dtype=torch.bool),
        "next": TensorDict({"observation": torch.rand(*shape, 6, generator=g),
                            "reward": torch.rand(*shape, 1, generator=g) * 3 - 1,
                            "done": torch.zeros(*shape, 1, dtype=torch.bool),
                            "terminated": torch.zeros(*shape, 1, dtype=torch.bool)}, batch_size=shape),
    }, batch_size=shape)


def _log_prob(loc, scale, noise):
    """log pi of tanh(loc + scale n) by hand: the Gaussian's log-density at the preimage minus log(1 - tanh^2)."""
    pre = loc + scale * noise
    gauss = -0.5 * noise ** 2 - torch.log(scale) - 0.5 * math.log(2 * math.pi)
    return (gauss - torch.log(1 - torch.tanh(pre) ** 2)).sum(-1)


def test_the_losses_over_a_horizon_with_an_episode_end_and_a_terminal_step_inside_it():
    """Sub-episode 0 reaches its episode's end after two of its three steps (mask); sub-episode 1's first step is
    terminal: its later steps do not count and its target does not bootstrap. Every term recomputed one
    sub-episode and step at a time."""
    cfg, t = training("tdmpc2", "algo.tdmpc2.horizon=3", "algo.tdmpc2.entropy=0.1", seeds=(A,))
    loss, model = t.loss, t.networks.actor_net
    batch = _sub_episodes(1, 2, 3)
    batch["mask"][0, 0, 2] = False
    batch["next", "terminated"][0, 1, 0] = True
    loss.draw(batch)
    scale_before = loss.q_scale.clone()
    out = loss(batch.clone())
    o, support, gamma, rho = cfg.algo.tdmpc2, loss.support, cfg.gamma, cfg.algo.tdmpc2.rho

    def q_logits(params, za, q):  # Q-network q's logits, alone
        named = {k: v[q] for k, v in params["module"].flatten_keys(".").items()}
        net = loss.qvalue_network.module.net
        return net.forward_with(za[None], [(named[f"net.layers.{i}.weight"], named[f"net.layers.{i}.bias"])
                                           for i in range(len(net.layers))],
                                [(named[f"net.norms.{i}.weight"], named[f"net.norms.{i}.bias"])
                                 for i in range(len(net.norms))])[0]

    def q_values(params, z, a):
        return [float(support.value(q_logits(params, torch.cat([z, a], -1), q))) for q in range(o.critics)]

    steps_of = {0: 2, 1: 1}  # the steps that count in each sub-episode
    totals = {"consistency": 0.0, "reward": 0.0, "value": 0.0}
    actor_terms, q_first = [], []
    with torch.no_grad():
        for b, steps in steps_of.items():
            z = model.encode(batch["observation"][0, b, 0][None])
            for step in range(steps):
                w = rho ** step
                a, r = batch["action"][0, b, step][None], batch["next", "reward"][0, b, step][None]
                terminal = float(batch["next", "terminated"][0, b, step])
                next_z = model.encode(batch["next", "observation"][0, b, step][None])
                loc, scale = model.pi(next_z)
                next_a = torch.tanh(loc + scale * batch[TARGET_NOISE_KEY][0, b, step][None])
                target = float(r) + gamma * (1 - terminal) * min(q_values(loss.target_qvalue_network_params, next_z,
                                                                          next_a))
                za = torch.cat([z, a], -1)
                totals["reward"] += w * float(cross_entropy(model.reward(za), two_hot(r, support)))
                value_ce = [float(cross_entropy(q_logits(loss.qvalue_network_params, za, q),
                                                two_hot(torch.tensor([[target]]), support)))
                            for q in range(o.critics)]
                totals["value"] += w * sum(value_ce) / o.critics
                ploc, pscale = model.pi(z)
                noise = batch[PRIOR_NOISE_KEY][0, b, step][None]
                q_mean = sum(q_values(loss.qvalue_network_params, z, torch.tanh(ploc + pscale * noise))) / o.critics
                if step == 0:
                    q_first.append(q_mean)
                actor_terms.append((w, float(_log_prob(ploc, pscale, noise)), q_mean))
                z = model.next(z, a)
                totals["consistency"] += w * float((z - next_z).square().mean())
    spread = 0.9 * abs(q_first[0] - q_first[1])  # the 95% and 5% quantiles of two values
    scale = scale_before + o.scale_tau * (spread - scale_before)
    torch.testing.assert_close(loss.q_scale, scale)
    actor = sum(w * (0.1 * logp - q / max(float(scale), 1.0)) for w, logp, q in actor_terms)
    expected = {"loss_consistency": o.consistency_weight * totals["consistency"] / 2 / 3,
                "loss_reward": o.reward_weight * totals["reward"] / 2 / 3,
                "loss_value": o.value_weight * totals["value"] / 2 / 3,
                "loss_actor": actor / 2 / 3}
    for key, value in expected.items():
        assert float(out[key].detach()) == pytest.approx(value, rel=1e-4, abs=1e-6), key


def test_the_prior_s_loss_reaches_the_prior_alone_and_the_model_s_losses_leave_it():
    cfg, t = training("tdmpc2", seeds=(A,))
    loss, model = t.loss, t.networks.actor_net
    batch = _sub_episodes(1, 4, cfg.algo.tdmpc2.horizon)
    loss.draw(batch)
    out = loss(batch)
    prior = set(map(id, model.pi.parameters()))
    out["loss_actor"].sum().backward(retain_graph=True)
    for name, p in model.named_parameters():
        assert (p.grad is not None and p.grad.abs().sum() > 0) == (id(p) in prior), name
    assert all(p.grad is None for p in loss.qvalue_network_params.values(True, True))
    model.zero_grad(set_to_none=True)
    (out["loss_consistency"] + out["loss_reward"] + out["loss_value"]).sum().backward()
    assert all(p.grad is None for p in model.pi.parameters())
    assert all(p.grad is not None for name, p in model.named_parameters() if not name.startswith("pi."))
    assert all(p.grad is not None for p in loss.qvalue_network_params.values(True, True))


# ------------------------------------------------------------------ the learner
@pytest.mark.slow
def test_a_planning_member_equals_its_solo_run_resumes_exactly_and_its_model_loads_as_a_policy(tmp_path):
    run = ["algo=tdmpc2", *SHORT, "episodes=5", "checkpoint_every=2"]
    solo = solo_and_resumed_pair(run, tmp_path)
    assert "critic/loss_consistency" in solo.splitlines()[0]
    cfg = load(*run)
    policy = make_policy("tdmpc2", {"actor_hidden": cfg.network.actor_hidden, "activation": cfg.network.activation},
                         6, torch.load(tmp_path / "solo" / "actor.pt"), algo=cfg.algo,
                         critic=torch.load(tmp_path / "solo" / "critic.pt"), gamma=cfg.gamma)
    assert policy(np.zeros(6)).shape == (2,)


@pytest.mark.parametrize("override, message", [
    (["er=prioritised"], "draws whole sub-episodes"),
    (["er.buffer_size=10100"], "multiple of the episode"),
    (["algo.td.n_step=3"], "set algo.td.n_step: 1"),
    (["algo.td.critic_blocks=2"], "networks are its own"),
    (["algo.td.pessimism=0.5"], "algo.td.pessimism is built for"),
    (["algo.tdmpc2.latent=30"], "multiple of algo.tdmpc2.group"),
    (["algo.tdmpc2.group=1"], "algo.tdmpc2.group must be >= 2"),
    (["algo.tdmpc2.policy_samples=64"], "must be below algo.tdmpc2.samples"),
    (["algo.tdmpc2.elites=65"], "at most algo.tdmpc2.samples"),
    (["algo.tdmpc2.rho=0"], "algo.tdmpc2.rho must be in"),
    (["algo.tdmpc2.max_std=0.01"], "is below algo.tdmpc2.min_std"),
    (["compile=true"], "runs eagerly"),
])
def test_tdmpc2_s_settings_are_checked(override, message):
    with pytest.raises(ConfigError, match=message):
        load("algo=tdmpc2", "er=memory", *override)


@pytest.mark.slow
def test_a_planning_run_s_policy_plans_with_its_saved_model_and_q_networks(tmp_path):
    """load_policy reads actor.pt and critic.pt: the policy plans (not the prior's tanh(loc)), drives the same
    actions in every episode from the same start (its draws restart with the episode), and evaluation in
    train.py (eval_seeds) scores it as evaluate.py does."""
    import json

    from engine.evaluation import evaluate, load_policy

    from tests.test_train import run_train

    result = run_train("algo=tdmpc2", *SHORT, "episodes=3", f"seed={A}", "eval_seeds=[11]", "eval_episodes=1",
                       f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    policy, settings = load_policy(tmp_path)
    assert type(policy.net).__name__ == "PlanningActor"
    obs = np.linspace(0.1, 0.6, 6)
    policy.reset()
    first = [policy(obs) for _ in range(3)]
    policy.reset()
    again = [policy(obs) for _ in range(3)]
    assert all(np.array_equal(a, b) for a, b in zip(first, again))
    with torch.no_grad():
        prior = torch.tanh(policy.net.net(torch.as_tensor(obs, dtype=torch.float32)[None, None])[0])[0, 0].numpy()
    assert not np.allclose(first[0], prior)  # MPPI's action, not the prior's mean
    summary = json.loads((tmp_path / "summary.json").read_text())
    scores = evaluate(policy, settings, [11], 1)
    assert summary["evaluation"]["tracks"]["11"] == pytest.approx(scores[11], abs=1e-4)
    (tmp_path / "critic.pt").unlink()
    with pytest.raises(Exception, match="holds no critic.pt"):
        load_policy(tmp_path)


@pytest.mark.slow
def test_without_planning_it_acts_and_evaluates_by_its_prior(tmp_path):
    from learners.latent import PlanningSampler

    cfg, t = training("tdmpc2", "algo.tdmpc2.planning=false", seeds=(A,))
    assert not isinstance(t.sampler, PlanningSampler)
    run = ["algo=tdmpc2", *SHORT, "episodes=2", "algo.tdmpc2.planning=false", f"seed={A}"]
    train_population(load(*run), tmp_path)
    cfg = load(*run)
    policy = make_policy("tdmpc2", {"actor_hidden": cfg.network.actor_hidden, "activation": cfg.network.activation},
                         6, torch.load(tmp_path / "actor.pt"), algo=cfg.algo)  # no critic needed: the prior's tanh(loc)
    obs = torch.linspace(0.1, 0.6, 6)
    with torch.no_grad():
        expected = torch.tanh(policy.net(obs[None, None])[0])[0, 0].clamp(-1, 1).numpy()
    np.testing.assert_array_equal(policy(obs.numpy()), expected)


@pytest.mark.parametrize("override", [["algo.tdmpc2.latent=65536", "algo.tdmpc2.width=65536"],
                                      ["algo.tdmpc2.samples=100000", "algo.tdmpc2.elites=100000",
                                       "algo.tdmpc2.iterations=1000"]])
def test_the_memory_estimate_sees_the_planner_s_own_sizes(override):
    from engine.config import RunConfig
    from engine.limits import check_ram

    with pytest.raises(ConfigError, match="this run needs about "):
        check_ram(RunConfig.compose("algo=tdmpc2", "er=memory", *override), available=16 * 2**30)
