"""Options of the off-policy learners for few samples: n-step TD targets (``algo.td.n_step``),
DroQ's Q-networks (``algo.td.critic_dropout``, ``algo.td.critic_layer_norm``; ``algo=droq``) and
BRO's (``algo.td.critic_blocks`` and the rest of ``algo=bro``: residual layer-normalised
Q-networks, weight decay, periodic resets) and REDQ (``algo=redq``: TorchRL's ``REDQLoss`` for
stacked members, each with its own random subsets of target networks).

Checked: the n-step transitions against sums written out by hand, TorchRL's TD target with them,
layer normalisation against ``torch.nn.LayerNorm``, dropout's masks and scaling, the residual
network against its formula, a reset against fresh networks drawn from the same generator states,
and whole runs: a member equals its solo run, an interrupted run resumes exactly, one step is the
old learner, a reset changes a run from its episode on and not before; REDQ's step against
TorchRL's ``REDQLoss`` (values and gradients) and its actor schedule.
"""

import re

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from collectors import STEPS_KEY, n_step_transitions
from engine.config import ConfigError
from engine.evaluation import make_policy
from engine.runner import train_population
from engine.setup import make_env, make_generators, make_learner
from learners.base import MetricTotals
from learners.networks import StackedDropout, StackedLayerNorm, StackedLinear, StackedResidualCriticNet, reset_parameters
from tests.test_config import load
from tests.test_offpolicy import A, B, FAST, training, transitions
from tests.test_resilience import interrupted_after

DROQ = ["algo.td.critic_dropout=0.1", "algo.td.critic_layer_norm=true"]
BRO = ["algo=bro", "algo.td.critic_width=32", "algo.td.critic_blocks=1"]  # small and quick


def episode_batch(rewards, done_at=()):
    """One car's ``[1, T]`` batch: rewards as given, observations numbered by step, done where asked."""
    steps = len(rewards)
    done = torch.zeros(1, steps, 1, dtype=torch.bool)
    for t in done_at:
        done[0, t] = True
    step = torch.arange(steps, dtype=torch.float32).reshape(1, steps, 1)
    return TensorDict({
        "observation": step.expand(1, steps, 6).clone(), "action": torch.zeros(1, steps, 2),
        "next": TensorDict({"observation": (step + 1).expand(1, steps, 6).clone(),
                            "reward": torch.tensor(rewards, dtype=torch.float32).reshape(1, steps, 1),
                            "done": done, "terminated": torch.zeros_like(done)}, batch_size=[1, steps]),
    }, batch_size=[1, steps])


def test_n_step_transitions_sum_discounted_rewards_and_stop_at_the_episode_end():
    g = 0.5
    batch = episode_batch([1.0, 2.0, 4.0, 8.0, 16.0, 32.0], done_at=(2, 5))  # two episodes of 3 steps
    out = n_step_transitions(batch, g, 3)
    r = [1.0, 2.0, 4.0, 8.0, 16.0, 32.0]
    expected = [r[0] + g * r[1] + g * g * r[2], r[1] + g * r[2], r[2],
                r[3] + g * r[4] + g * g * r[5], r[4] + g * r[5], r[5]]
    assert out["next", "reward"].flatten().tolist() == expected
    assert out[STEPS_KEY].flatten().tolist() == [3, 2, 1, 3, 2, 1]
    assert out["next", "observation"][0, :, 0].tolist() == [3, 3, 3, 6, 6, 6]  # the state after the window
    assert out["next", "done"].flatten().tolist() == [True] * 6
    assert torch.equal(out["observation"], batch["observation"]) and torch.equal(out["action"], batch["action"])
    assert batch["next", "reward"].flatten().tolist() == r  # the collected batch is left as it was
    # n = 2 in an episode that runs on past the batch's end (the sum stops at the last step)
    out = n_step_transitions(episode_batch([1.0, 2.0, 4.0]), g, 2)
    assert out["next", "reward"].flatten().tolist() == [2.0, 4.0, 4.0]
    assert out[STEPS_KEY].flatten().tolist() == [2, 2, 1]
    # n = 1: the one-step transitions themselves
    one = n_step_transitions(batch, g, 1)
    assert torch.equal(one["next", "reward"], batch["next", "reward"]) and one[STEPS_KEY].eq(1).all()


def test_members_get_the_n_step_transitions_they_get_alone():
    data = transitions(3, 200, seed=4)
    data["next", "done"][:, -1] = True
    both = n_step_transitions(data, 0.9, 4)
    for r in range(3):
        alone = n_step_transitions(data[r:r + 1], 0.9, 4)
        assert torch.equal(both["next", "reward"][r:r + 1], alone["next", "reward"])


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_torchrl_targets_bootstrap_with_gamma_to_the_steps(algo):
    cfg, t = training(algo, "gamma=0.9")
    data = transitions(2, 5)
    data.set(STEPS_KEY, torch.tensor([1.0, 2, 3, 3, 1]).expand(2, 5).unsqueeze(-1).clone())
    next_value = torch.full((2, 5, 1), 10.0)
    target = t.loss.value_estimator.value_estimate(data, next_value=next_value)
    expected = data["next", "reward"] + 0.9 ** data[STEPS_KEY] * 10.0
    torch.testing.assert_close(target, expected)


def test_stacked_layer_norm_is_torch_layer_norm_per_member():
    x = torch.randn(3, 7, 100, generator=torch.Generator().manual_seed(0))
    norm = StackedLayerNorm(3, 100)
    with torch.no_grad():
        norm.weight.uniform_(0.5, 1.5)
        norm.bias.uniform_(-1, 1)
    for r in range(3):
        reference = torch.nn.functional.layer_norm(x[r], (100,), norm.weight[r], norm.bias[r], eps=1e-5)
        torch.testing.assert_close(norm(x)[r], reference, rtol=1e-5, atol=1e-5)
        alone = StackedLayerNorm(1, 100)
        alone.load_state_dict({"weight": norm.weight[r:r + 1], "bias": norm.bias[r:r + 1]})
        assert torch.equal(alone(x[r:r + 1])[0], norm(x)[r])


def test_dropout_keeps_units_at_its_rate_scaled_and_draws_each_member_alone():
    gens = [torch.Generator().manual_seed(s) for s in (1, 2)]
    drop = StackedDropout(0.25, gens)
    out = drop(torch.ones(2, 400, 100))
    kept = out.ne(0)
    assert abs(kept.float().mean().item() - 0.75) < 0.01
    assert torch.equal(out[kept], torch.full_like(out[kept], 1 / 0.75))
    alone = StackedDropout(0.25, [torch.Generator().manual_seed(2)])(torch.ones(1, 400, 100))
    assert torch.equal(alone[0], out[1])
    drop.eval()
    assert torch.equal(drop(out), out)


@pytest.mark.slow
def test_each_member_equals_its_solo_run(tmp_path):
    run = ["algo=sac", "er=memory", *FAST, "algo.td.updates_per_step=0.1", "algo.td.n_step=3", *DROQ]
    train_population(load(*run, f"seed={B}"), tmp_path / "solo")
    train_population(load(*run, f"seeds=[{B},{A}]"), tmp_path / "pair")
    assert ((tmp_path / "pair" / f"seed{B}" / "metrics.csv").read_bytes()
            == (tmp_path / "solo" / "metrics.csv").read_bytes())


@pytest.mark.slow
def test_an_interrupted_droq_run_resumes_exactly(tmp_path):
    """The dropout masks come from the members' generators, which the checkpoint saves."""
    run = ["algo=sac", "er=prioritised", *FAST, "episodes=5", "checkpoint_every=2", f"seeds=[{A},{B}]",
           "algo.td.n_step=3", *DROQ]
    train_population(load(*run), tmp_path / "reference")
    with interrupted_after(3):
        train_population(load(*run), tmp_path / "run")
    train_population(load(*run), tmp_path / "run")
    for seed in (A, B):
        assert ((tmp_path / "run" / f"seed{seed}" / "metrics.csv").read_bytes()
                == (tmp_path / "reference" / f"seed{seed}" / "metrics.csv").read_bytes())


@pytest.mark.slow
def test_the_options_change_the_run_and_their_defaults_do_not(tmp_path):
    run = ["algo=sac", "er=memory", *FAST, "algo.td.updates_per_step=0.1", f"seed={A}"]
    train_population(load(*run), tmp_path / "plain")
    train_population(load(*run, "algo.td.n_step=1", "algo.td.critic_dropout=0.0",
                          "algo.td.critic_layer_norm=false"), tmp_path / "defaults")
    train_population(load(*run, "algo.td.n_step=3"), tmp_path / "nstep")
    plain = (tmp_path / "plain" / "metrics.csv").read_bytes()
    assert (tmp_path / "defaults" / "metrics.csv").read_bytes() == plain
    assert (tmp_path / "nstep" / "metrics.csv").read_bytes() != plain


def test_the_residual_critic_is_its_formula_per_member():
    torch.manual_seed(0)
    net = StackedResidualCriticNet(2, 8, 16, blocks=2, activation="relu")
    reset_parameters(net, [torch.Generator().manual_seed(s) for s in (1, 2)])
    with torch.no_grad():  # scales and shifts away from 1 and 0, so that they count
        for norm in net.norms:
            norm.weight.uniform_(0.5, 1.5)
            norm.bias.uniform_(-0.5, 0.5)
    obs, act = torch.randn(2, 5, 6), torch.randn(2, 5, 2)
    out = net(obs, act)
    for r in range(2):
        def lin(layer, x):
            return x @ layer.weight[r].T + layer.bias[r]

        def ln(i, x):
            n = net.norms[i]
            return torch.nn.functional.layer_norm(x, (16,), n.weight[r], n.bias[r], eps=1e-5)

        h = torch.relu(ln(0, lin(net.embed, torch.cat([obs[r], act[r]], -1))))
        for b in range(2):
            h = h + ln(2 + 2 * b, lin(net.layers[2 * b + 1], torch.relu(ln(1 + 2 * b, lin(net.layers[2 * b], h)))))
        torch.testing.assert_close(out[r], lin(net.head, h), rtol=1e-5, atol=1e-5)
    alone = StackedResidualCriticNet(1, 8, 16, blocks=2, activation="relu")
    alone.load_state_dict({k: v[1:] for k, v in net.state_dict().items()})
    assert torch.equal(alone(obs[1:], act[1:]), out[1:])  # a member computes what it computes alone


def test_a_reset_draws_the_networks_anew_as_at_the_start_and_restarts_the_optimisers():
    bro = ("algo.td.critic_width=32", "algo.td.critic_blocks=1")
    cfg, t = training("bro", *bro, "algo.td.reset_every=7")
    t.phases.updates = lambda e: (0, 3)
    t.phases.run(transitions(2, 300), 16, MetricTotals(), 1)  # trains: moments, temperature, targets move
    states = [g.get_state() for g in t.phases.generators]
    t.phases.run(transitions(2, 300), 16, MetricTotals(), 7)  # resets, then takes its 3 steps
    # a learner built from the generators as they stood, taking the same 3 steps
    generators = make_generators((A, B))
    for g, state in zip(generators, states):
        g.set_state(state)
    fresh = make_learner(load("algo=bro", "er=memory", f"seeds=[{A},{B}]", *bro), make_env(cfg, (A, B)), generators)
    fresh.phases.updates = lambda e: (0, 3)
    fresh.phases.run(transitions(2, 300), 16, MetricTotals(), 7)
    for ours, theirs in ((t.loss.actor_network_params, fresh.loss.actor_network_params),
                         (t.loss.qvalue_network_params, fresh.loss.qvalue_network_params),
                         (t.loss.target_qvalue_network_params, fresh.loss.target_qvalue_network_params)):
        for key, value in theirs.items(True, True):
            assert torch.equal(ours[key], value), key
    assert torch.equal(t.loss.log_alpha, fresh.loss.log_alpha)
    assert t.optimisers.critic.steps == t.optimisers.actor.steps == 3
    for a, b in zip(t.optimisers.critic.exp_avg_sq + t.optimisers.actor.exp_avg,
                    fresh.optimisers.critic.exp_avg_sq + fresh.optimisers.actor.exp_avg):
        assert torch.equal(a, b)


@pytest.mark.parametrize("algo", ["td3", "tqc", "crossq"])
def test_a_reset_sets_every_target_network_to_its_new_online_network(algo):
    """... and CrossQ's batch-norm statistics back to their start (it has no target networks)."""
    _, t = training(algo, ("+" if algo == "crossq" else "") + "algo.td.reset_every=7")
    t.phases.updates = lambda e: (0, 3)
    t.phases.run(transitions(2, 300), 16, MetricTotals(), 1)
    before = t.loss.actor_network_params.clone()
    t.phases.reset_networks()
    for online, target in (("actor_network_params", "target_actor_network_params"),
                           ("qvalue_network_params", "target_qvalue_network_params")):
        if hasattr(t.loss, target):
            online, target = getattr(t.loss, online), getattr(t.loss, target)
            for key in target.keys(True, True):
                assert torch.equal(online[key], target[key]), key
    statistics = {k: v for k, v in t.loss.qvalue_network_params.items(True, True) if k[-1].startswith("running")}
    assert (algo == "crossq") == bool(statistics)
    for key, value in statistics.items():
        assert torch.equal(value, torch.zeros_like(value) if key[-1] == "running_mean" else torch.ones_like(value)), key
    assert not any(torch.equal(before[k], v) for k, v in t.loss.actor_network_params.items(True, True) if k[-1] == "weight")
    assert t.optimisers.actor.steps == t.optimisers.critic.steps == 0


@pytest.mark.slow
def test_a_reset_changes_a_run_from_its_episode_on(tmp_path):
    run = [*BRO, "er=memory", *FAST, "episodes=6", "algo.td.updates_per_step=0.1", f"seed={A}"]
    train_population(load(*run), tmp_path / "plain")
    train_population(load(*run, "algo.td.reset_every=4"), tmp_path / "reset")
    plain, reset = ((tmp_path / name / "metrics.csv").read_text().splitlines() for name in ("plain", "reset"))
    assert plain[:5] == reset[:5]  # the header and episodes 0-3
    assert plain[5] != reset[5]  # episode 4 trains on reset networks


@pytest.mark.slow
def test_bro_members_equal_their_solo_runs_and_resume_exactly_across_a_reset(tmp_path):
    assert_member_is_solo_and_resumes(tmp_path, [*BRO, "er=prioritised", *FAST, "episodes=5",
                                                 "algo.td.updates_per_step=0.1", "algo.td.reset_every=3"])


def assert_member_is_solo_and_resumes(tmp_path, run: list[str]) -> None:
    """Member B of a pair computes its solo run, and so does a pair interrupted after episode 3
    and resumed from its checkpoint (metrics bytes)."""
    train_population(load(*run, f"seed={B}"), tmp_path / "solo")
    train_population(load(*run, f"seeds=[{B},{A}]"), tmp_path / "pair")
    with interrupted_after(3):
        train_population(load(*run, f"seeds=[{B},{A}]", "checkpoint_every=2"), tmp_path / "resumed")
    train_population(load(*run, f"seeds=[{B},{A}]", "checkpoint_every=2"), tmp_path / "resumed")
    solo = (tmp_path / "solo" / "metrics.csv").read_bytes()
    for folder in ("pair", "resumed"):
        assert (tmp_path / folder / f"seed{B}" / "metrics.csv").read_bytes() == solo, folder


def test_weight_decay_shrinks_only_the_q_networks(tmp_path):
    _, t = training("bro", "algo.td.critic_width=32", "algo.td.critic_blocks=1")
    assert t.optimisers.critic.weight_decay == pytest.approx(1e-4) and t.optimisers.actor.weight_decay == 0
    assert isinstance(t.networks.qvalue_nets[0], StackedResidualCriticNet)
    assert isinstance(t.networks.qvalue_nets[0].embed, StackedLinear)


@pytest.mark.parametrize("override, message", [
    (["algo=sac", "algo.td.n_step=0"], "n_step must be >= 1"),
    (["algo=sac", "algo.td.n_step=1.5"], "n_step must be an integer"),
    (["algo=sac", "algo.td.critic_dropout=1.0"], "critic_dropout must be in [0, 1)"),
    (["algo=sac", "algo.td.critic_layer_norm=3"], "critic_layer_norm must be"),
    (["algo=crossq", "+algo.td.critic_layer_norm=true"], "batch-normalised"),
    (["algo=sac", "algo.td.critic_dropout=0.01", "compile=true"], "not supported with algo.td.critic_dropout"),
    (["algo=bro", "algo.td.critic_dropout=0.01"], "residual Q-network, layer-normalised throughout"),
    (["algo=sac", "algo.td.critic_width=64"], "need algo.td.critic_blocks >= 1"),
    (["algo=bro", "algo.td.critic_activation=gelu"], "critic_activation must be one of tanh, relu, elu"),
    (["algo=bro", "algo.td.reset_every=-1"], "reset_every must be >= 0"),
    (["algo=bro", "algo.td.critic_weight_decay=-0.1"], "critic_weight_decay must be >= 0"),
    (["algo=crossq", "+algo.td.critic_blocks=2"], "algo.td.critic_blocks: 0"),
])
def test_bad_settings_are_refused_with_a_reason(override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        load(*override)


def test_the_budget_table_reads_a_run_s_final_performance_at_shorter_budgets(tmp_path, capsys, monkeypatch):
    """A run of 4 episodes gives what a run of 2 reports as its final performance (the same first
    episodes), and its own at 4; the table says so per track, and with the oracle's scores of the
    tracks, each budget's and the deterministic policy's mean fraction of them."""
    from analysis import budget

    monkeypatch.setattr(budget, "read_oracles", lambda: {A: 100.0, B: 50.0})

    run = ["algo=sac", "er=memory", *FAST, "final_window=2", "eval_seeds=[1]", "eval_episodes=1"]
    train_population(load(*run, "episodes=2", f"seed={A}"), tmp_path / "short")
    train_population(load(*run, "episodes=4", f"seeds=[{A},{B}]"), tmp_path / "long")
    assert budget.main([str(tmp_path / "long"), "--budgets", "2", "4", "--window", "2",
                        "--table", str(tmp_path / "budget.csv")]) == 0
    import json

    short = json.loads((tmp_path / "short" / "summary.json").read_text())
    rows = {(int(r.split(",")[2]), int(r.split(",")[3])): r.split(",")
            for r in (tmp_path / "budget.csv").read_text().splitlines()[1:]}
    header = (tmp_path / "budget.csv").read_text().splitlines()[0].split(",")
    assert header == ["algo", "er", "track", "budget", "final", "oracle", "fraction", "evaluation"]
    assert float(rows[A, 2][4]) == pytest.approx(short["final_mean"], abs=1e-6)
    assert rows[A, 2][7] == "" and rows[A, 4][7] != ""  # the evaluation belongs to the run's own end
    out = capsys.readouterr().out
    assert f"| {A} | " in out and f"| {B} | " in out and "2 episodes: " in out and "4 episodes: " in out
    assert float(rows[A, 4][6]) == pytest.approx(float(rows[A, 4][4]) / 100.0, abs=1e-6)
    ends = [float(rows[A, 4][7]) / 100.0, float(rows[B, 4][7]) / 50.0]
    assert f"deterministic policy at the end: {sum(ends) / 2:.3f} of the oracle [" in out


# ---------------------------------------------------------------------------- REDQ
REDQ = ["algo=redq", "algo.redq.critics=3", "algo.redq.subset=2", "algo.redq.policy_delay=2"]  # small and quick


@pytest.mark.parametrize("bounds", [None, (0.1, 10.0)])
def test_redq_of_a_population_of_one_equals_torchrl_redq_loss(bounds):
    """``MemberREDQLoss.population_losses`` for one member gives TorchRL's ``REDQLoss`` (values and every gradient) on the
    same networks, the same subset of target networks and the same N(0, I) draws; with TorchRL's
    bounds on the temperature, a temperature below them is raised in every term and the
    temperature's gradient passes the bound."""
    from torch.distributions.utils import _standard_normal
    from torchrl.objectives import REDQLoss, SoftUpdate

    from losses.td import ACTION_NOISE_KEY
    from tests.test_offpolicy import _plain_actor

    extra = [f"algo.redq.min_alpha={bounds[0]}", f"algo.redq.max_alpha={bounds[1]}"] if bounds else []
    cfg, t = training("redq", "algo.redq.critics=4", *extra, seeds=(A,))
    low, high = bounds or (1e-30, 1e30)
    plain = REDQLoss(_plain_actor(t), t.networks.qvalues, num_qvalue_nets=4, sub_sample_len=2, loss_function="l2",
                     alpha_init=1.0, min_alpha=low, max_alpha=high, target_entropy=-2.0, deactivate_vmap=True)
    plain.make_value_estimator(gamma=cfg.gamma)
    SoftUpdate(plain, tau=0.005)
    plain.qvalue_network_params.data.copy_(t.loss.qvalue_network_params.data)
    plain.target_qvalue_network_params.data.copy_(t.loss.target_qvalue_network_params.data)
    if bounds:  # a temperature below the lower bound
        with torch.no_grad():
            plain.log_alpha.fill_(-4.0)
            t.loss.log_alpha.fill_(-4.0)
    data = transitions(1, 64)
    torch.manual_seed(1)  # TorchRL draws its subset, then the actor's and the target's noise in one tensor
    subset = torch.randperm(4)[:2].sort()[0]
    noise = _standard_normal((2, 1, 64, 2), dtype=torch.float32, device="cpu")
    mine = data.clone().update({ACTION_NOISE_KEY: noise[0], ("next", ACTION_NOISE_KEY): noise[1]})
    t.loss.subsets = subset.view(2, 1)
    ours_params = [*t.loss.actor_network_params.values(True, True), t.loss.log_alpha,
                   *t.loss.qvalue_network_params.values(True, True)]
    their_params = [*plain.actor_network_params.values(True, True), plain.log_alpha,
                    *plain.qvalue_network_params.values(True, True)]
    actor_count = len(list(t.networks.actor_net.parameters()))
    for term in ("loss_qvalue", "loss_actor", "loss_alpha"):
        torch.manual_seed(1)
        theirs = plain(data.clone())[term]
        ours = t.loss.population_losses(t.networks.actor_net, mine)[0][term]
        torch.testing.assert_close(ours[0], theirs, rtol=1e-6, atol=1e-6)
        our_grads = torch.autograd.grad(ours.sum(), ours_params, allow_unused=True)
        their_grads = torch.autograd.grad(theirs, their_params, allow_unused=True)
        for a, b in zip(our_grads, their_grads):
            if b is None or not b.any():
                assert a is None or not a.any()
            else:
                torch.testing.assert_close(a.reshape(b.shape), b, rtol=1e-5, atol=1e-7)  # log_alpha: [1] and []
        reached = [g is not None and g.any() for g in our_grads]
        owners = {"loss_qvalue": [False] * (actor_count + 1) + [True] * (len(reached) - actor_count - 1),
                  "loss_actor": [True] * actor_count + [False] * (len(reached) - actor_count),
                  "loss_alpha": [False] * actor_count + [True] + [False] * (len(reached) - actor_count - 1)}
        assert reached == owners[term], term
    if bounds:
        torch.testing.assert_close(t.loss.alpha, torch.tensor([0.1]))  # exp(log 0.1)


@pytest.mark.slow
def test_redq_members_draw_their_own_subsets_and_equal_their_solo_runs(tmp_path):
    """Each member's subset of target networks comes from its generator (members differ); a member
    equals its solo run and an interrupted population resumes exactly (prioritised replay)."""
    _, t = training("redq", "algo.redq.critics=10")
    batch = transitions(2, 8)
    drawn = []
    for _ in range(20):
        t.loss.draw(batch)
        drawn.append(t.loss.subsets.clone())
    subsets = torch.stack(drawn)  # [draws, subset, R]
    assert subsets.shape == (20, 2, 2) and not torch.equal(subsets[..., 0], subsets[..., 1])
    assert (subsets[:, 0] < subsets[:, 1]).all()  # distinct networks, in increasing order
    run = [*REDQ, "er=prioritised", *FAST, "episodes=6", "algo.td.updates_per_step=0.1", "algo.redq.policy_delay=1"]
    assert_member_is_solo_and_resumes(tmp_path, run)  # a temperature step every critic step: before its loss summed
    #   each member's terms alone, a member's temperature drifted from its solo run's by episode 4 here
    cfg = load(*run)
    policy = make_policy("redq", {"actor_hidden": cfg.network.actor_hidden, "activation": cfg.network.activation}, 6,
                         torch.load(tmp_path / "solo" / "actor.pt"))  # evaluate.py's policy of the run
    assert policy(np.zeros(6)).shape == (2,)


def test_redq_steps_the_actor_once_every_policy_delay_critic_steps():
    _, t = training("redq", *REDQ[1:-1], "algo.redq.policy_delay=3")
    steps = {"actor": 0, "critic": 0}
    for name in steps:
        optimiser = getattr(t.optimisers, name)
        original = optimiser.step

        def counted(original=original, name=name):
            steps[name] += 1
            original()
        optimiser.step = counted
    actor_before = [p.detach().clone() for p in t.networks.actor_net.parameters()]
    t.phases.updates = lambda episode: (0, 7)
    totals = MetricTotals()
    t.phases.run(transitions(2, 300), 16, totals, episode=5)
    assert steps == {"critic": 7, "actor": 2}  # after critic steps 3 and 6
    assert all(not torch.equal(a, b) for a, b in zip(actor_before, t.networks.actor_net.parameters()))
    assert {"critic/loss_qvalue", "actor/loss_actor", "actor/loss_alpha", "actor/alpha"} <= set(totals.means(2)[0])


@pytest.mark.parametrize("override, message", [
    (["algo=redq", "algo.redq.subset=10"], "subset must be below algo.redq.critics (10)"),
    (["algo=redq", "algo.redq.critics=1"], "critics must be >= 2"),
    (["algo=redq", "algo.redq.policy_delay=0"], "policy_delay must be >= 1"),
    (["algo=redq", "algo.redq.min_alpha=2.0", "algo.redq.max_alpha=1.0"], "min_alpha (2.0) is above"),
    (["algo=redq", "algo.td.critic_dropout=0.01"], "loss redq's step computes plain or residual Q-networks"),
    (["algo=sac", "+algo.redq.critics=4"], "a 'redq:' block does not apply to loss sac"),
])
def test_bad_redq_settings_are_refused_with_a_reason(override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        load(*override)


def test_redq_refuses_to_compile_with_a_reason():
    with pytest.raises(ConfigError, match=re.escape("compile=true is not supported for redq")):
        load("algo=redq", "compile=true")


def test_redq_takes_one_actor_step_per_environment_step_by_default():
    assert training("redq")[1].phases.policy_delay == 5  # the default: 5 updates per step
    assert training("redq", "algo.td.updates_per_step=20.0")[1].phases.policy_delay == 20
    assert training("redq", "algo.td.updates_per_step=10.0")[1].phases.policy_delay == 10
    assert training("redq", "algo.td.updates_per_step=0.3")[1].phases.policy_delay == 1
    assert training("redq", "algo.redq.policy_delay=7")[1].phases.policy_delay == 7
