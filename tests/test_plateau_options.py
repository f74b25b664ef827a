"""The off-policy learners' options that test what they share (docs/journal/2026-11-tuning.md, "What the learners share"):
running observation normalisation (``algo.td.observation_norm``), a falling entropy target
(``algo.sac.target_entropy_end``) and Q-networks that also see the car's true state
(``algo.td.privileged_critic``) or its own past observations and actions (``algo.td.critic_history``); the
discount is the run's ``gamma``.

Checked: the statistics against numpy's mean and variance in float64, per member; the minibatch's
observations normalised and the memory left raw; the entropy target's schedule by hand; the true state
against a hand computation and the history against the steps it records, both in both collectors bit for
bit, through TorchRL's spec check and (the history) across a save mid-episode; whole runs: a
member equals its solo run and an interrupted run resumes exactly with the options, the defaults leave a
run's bits alone, the saved actor (with its statistics) evaluates as the run evaluated it, and the fused
step with the true state is TorchRL's ``SACLoss`` with the state among its Q-networks' keys
(tests/test_offpolicy.py).
"""

import json
import math
import re

import numpy as np
import pytest
import torch

from engine.config import ConfigError
from engine.evaluation import evaluate, load_policy
from engine.runner import train_population
from learners.networks import NormalisedActor, ObservationNorm
from learners.td import linear_schedule
from tests.test_config import load
from tests.test_few_samples import assert_member_is_solo_and_resumes
from tests.test_offpolicy import A, B, FAST, training, transitions
from tests.test_train import run_train

BOTH = ["algo.td.observation_norm=true", "algo.sac.target_entropy_end=-6"]


def test_the_running_statistics_are_each_member_s_mean_and_variance_so_far():
    g = torch.Generator().manual_seed(3)
    seen = torch.rand(40, 3, 6, generator=g) * torch.tensor([1.0, 0.5, 3.0, 0.1, 2.0, 0.0])  # a constant input
    norm = ObservationNorm(3, 6)
    for x in seen:
        norm.update(x)
    data = seen.double().numpy()
    mean, var = data.mean(0), data.var(0)  # [3, 6]: per member, the population variance
    np.testing.assert_allclose(norm.mean.numpy(), mean, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose((norm.m2 / norm.count.unsqueeze(-1)).numpy(), var, rtol=1e-10, atol=1e-15)
    x = torch.rand(3, 5, 6, generator=g)  # [R, batch, obs]
    x[..., 5] = 0.0
    expected = (x.double().numpy() - mean[:, None]) / np.sqrt(var[:, None] + ObservationNorm.EPS)
    out = norm(x)
    assert out.dtype == torch.float32
    np.testing.assert_allclose(out.double().numpy(), expected.clip(-10, 10), rtol=1e-6, atol=1e-6)
    assert torch.equal(out[..., 5], torch.zeros(3, 5))  # a constant input at its constant becomes 0
    assert out[..., 3].abs().max() > 1 and out.abs().max() <= 10  # ... and is clipped elsewhere
    assert torch.equal(norm(x + 1)[..., 5], torch.full((3, 5), 10.0))
    # member 0's numbers do not depend on member 1's observations
    other = ObservationNorm(3, 6)
    for x_t in seen:
        other.update(torch.cat([x_t[:1], x_t[1:] * 7]))
    assert torch.equal(other(x)[0], out[0]) and torch.equal(other.mean[0], norm.mean[0])
    # sub-episodes ([R, size, length, obs]) broadcast the same way
    assert torch.equal(norm(x.unsqueeze(2))[:, :, 0], out)


def test_a_minibatch_is_normalised_as_the_statistics_stand_and_the_memory_stays_raw():
    cfg, learner = training("sac", "algo.td.observation_norm=true")
    norm, phases = learner.networks.norm, learner.phases
    assert phases.norm is norm and learner.sampler.norm is norm
    data = transitions(2, 50, seed=1)
    for x in data["observation"].unbind(1):
        learner.sampler.norm.update(x)
    raw = data.clone()
    batch = phases.normalised(data[:, :10].clone())
    assert torch.equal(batch["observation"], norm(raw["observation"][:, :10]))
    assert torch.equal(batch["next", "observation"], norm(raw["next", "observation"][:, :10]))
    assert torch.equal(data["observation"], raw["observation"])
    # acting: the sampler updates the statistics with what it sees, a paused probe does not
    count = norm.count.clone()
    learner.sampler(torch.rand(2, 6))
    assert torch.equal(norm.count, count + 1)
    with learner.sampler.paused():
        learner.sampler(torch.rand(2, 6))
    assert torch.equal(norm.count, count + 1)
    assert isinstance(learner.networks.policy_net, NormalisedActor)


def test_the_entropy_target_falls_linearly_from_the_first_gradient_step_to_the_last_episode():
    assert linear_schedule(-2.0, -6.0, 0, 1, 10) == -2.0
    assert linear_schedule(-2.0, -6.0, 1, 1, 10) == -2.0
    assert linear_schedule(-2.0, -6.0, 4, 1, 10) == pytest.approx(-2.0 - 4.0 / 3)
    assert linear_schedule(-2.0, -6.0, 10, 1, 10) == -6.0
    assert linear_schedule(-2.0, -6.0, 12, 1, 10) == -6.0
    _, learner = training("sac", "episodes=12", "algo.td.warmup_episodes=1", "algo.sac.target_entropy_end=-6")
    targets = []
    for episode in (0, 1, 6, 11):
        learner.phases.set_target_entropy(episode)
        targets.append(float(learner.loss.target_entropy))
    assert targets == [-2.0, -2.0, -4.0, -6.0]  # from the loss's own start, -(action dimensions)
    _, learner = training("redq", "episodes=11", "algo.sac.target_entropy=-1", "algo.sac.target_entropy_end=-3")
    learner.phases.set_target_entropy(10)
    assert float(learner.loss.target_entropy) == -3.0
    _, plain = training("sac")
    assert plain.phases.entropy_schedule is None and plain.phases.norm is None


@pytest.mark.slow
def test_members_equal_their_solo_runs_and_resume_exactly_with_both_options(tmp_path):
    assert_member_is_solo_and_resumes(tmp_path, ["algo=sac", "er=prioritised", *FAST, "episodes=5",
                                                 "algo.td.updates_per_step=0.1", *BOTH])


@pytest.mark.slow
def test_the_options_change_the_run_and_their_defaults_do_not(tmp_path):
    run = ["algo=sac", "er=memory", *FAST, "algo.td.updates_per_step=0.1", f"seed={A}"]
    train_population(load(*run), tmp_path / "plain")
    train_population(load(*run, "algo.td.observation_norm=false", "algo.sac.target_entropy_end=null"),
                     tmp_path / "defaults")
    plain = (tmp_path / "plain" / "metrics.csv").read_bytes()
    assert (tmp_path / "defaults" / "metrics.csv").read_bytes() == plain
    for name, option in (("norm", BOTH[0]), ("entropy", BOTH[1])):
        train_population(load(*run, option), tmp_path / name)
        assert (tmp_path / name / "metrics.csv").read_bytes() != plain, name


@pytest.mark.parametrize("algo", [pytest.param("sac", marks=pytest.mark.slow), "td3"])
def test_the_saved_actor_keeps_its_statistics_and_evaluates_as_the_run_did(tmp_path, algo):
    result = run_train(f"algo={algo}", "er=memory", *FAST[1:], "episodes=4", "algo.td.updates_per_step=0.1",
                       f"seed={B}", "eval_seeds=[1001]", "eval_episodes=1", "algo.td.observation_norm=true",
                       f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    policy, settings = load_policy(tmp_path / "run")
    assert isinstance(policy.net, NormalisedActor) and float(policy.net.norm.count[0]) == 4 * 200
    scores = evaluate(policy, settings, [B, 1001], 1)
    assert scores[B] == summary["evaluation"]["own_track"] and scores[1001] == summary["evaluation"]["tracks"]["1001"]


def test_the_true_state_is_progress_offset_and_heading_in_the_track_s_frame():
    from racing.sim import RacingSim

    sim = RacingSim(2, [1001, 1002])
    sim.seed([0, 1])
    sim.reset()
    track = sim.tracks[1]
    centre = (track.left_wall + track.right_wall) / 2
    a, b = centre[7], centre[8]
    u = (b - a) / np.linalg.norm(b - a)
    normal = np.array([-u[1], u[0]])  # counter-clockwise of the direction
    sim.checkpoint[1] = 7
    sim.x[1], sim.y[1] = a + 0.25 * (b - a) + 30.0 * normal
    heading = np.array([u[0] + normal[0], u[1] + normal[1]]) / np.sqrt(2)  # 45 degrees to the left of the segment
    sim.theta[1] = np.arctan2(heading[0], heading[1])  # the car moves along (sin theta, cos theta)
    state = sim.true_state()
    np.testing.assert_allclose(state[1], [(7 + 0.25) / sim.config.num_segments, 30.0 / sim.config.half_width, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-12)
    assert state.shape == (2, 4) and state[0, 0] < 0.05  # the other car at its start
    sim.x[1], sim.y[1] = a - 10.0 * u  # behind the segment's start: its progress does not go below the checkpoint
    assert sim.true_state()[1, 0] == 7 / sim.config.num_segments


def test_the_env_carries_the_true_state_in_both_collectors_bit_for_bit():
    from torchrl.envs import check_env_specs

    from racing.torchrl_env import RacingTorchEnv
    from tests.test_collectors import COMPARED, collect

    check_env_specs(RacingTorchEnv(3, track_seeds=[1, 2, 3], privileged=True))
    keys = [*COMPARED, ("privileged",), ("next", "privileged")]
    direct = collect("direct", steps=70, episodes=3, privileged=True)
    reference = collect("torchrl", steps=70, episodes=3, privileged=True)
    for ours, theirs in zip(direct, reference, strict=True):
        for key in keys:
            assert torch.equal(ours[key], theirs[key]), key
    plain = collect("direct", steps=70, episodes=3)
    for ours, theirs in zip(direct, plain, strict=True):  # the state is read, never changes the drive
        assert torch.equal(ours["next", "observation"], theirs["next", "observation"])
        assert "privileged" not in theirs.keys()
    batch = direct[0]  # the root's state is the previous step's next state, a reset car's fresh one
    assert torch.equal(batch["privileged"][:, 1:], batch["next", "privileged"][:, :-1])


def test_the_history_holds_the_last_observations_and_actions_of_the_episode_newest_first():
    from racing.torchrl_env import RacingTorchEnv

    env = RacingTorchEnv(2, track_seeds=[1, 2], history=3)
    seen = [env.reset_tensors()]
    first = seen[0]["observation"]
    assert torch.equal(seen[0]["history"], torch.cat([first, first, first, torch.zeros(2, 6)], 1))
    actions = [torch.tensor([[0.5, 0.1], [1.0, -0.2]]), torch.tensor([[2.0, 0.0], [-0.3, 0.4]]),
               torch.tensor([[0.9, -0.9], [0.2, 0.2]]), torch.tensor([[0.1, 0.3], [0.7, -0.5]])]
    for action in actions:
        seen.append(env.step_tensors(action))
    obs = [e["observation"] for e in seen]
    clipped = [a.clamp(-1, 1) for a in actions]
    assert torch.equal(seen[2]["history"], torch.cat([obs[1], obs[0], obs[0], clipped[1], clipped[0],
                                                      torch.zeros(2, 2)], 1))
    assert torch.equal(seen[4]["history"], torch.cat([obs[3], obs[2], obs[1], clipped[3], clipped[2], clipped[1]], 1))
    again = env.reset_tensors(torch.tensor([False, True]))  # car 1 starts a new episode, car 0 goes on
    assert torch.equal(again["history"][0], seen[4]["history"][0])
    fresh = again["observation"][1]
    assert torch.equal(again["history"][1], torch.cat([fresh, fresh, fresh, torch.zeros(6)]))
    # saved mid-episode and restored into a new environment, it continues exactly
    state = env.sim_state()
    twin = RacingTorchEnv(2, track_seeds=[1, 2], history=3)
    twin.load_sim_state(state)
    assert torch.equal(twin.reset_tensors()["history"], again["history"])
    step = torch.tensor([[0.3, 0.3], [0.6, -0.1]])
    assert torch.equal(twin.step_tensors(step)["history"], env.step_tensors(step)["history"])
    with pytest.raises(ValueError, match="no history"):
        RacingTorchEnv(2, track_seeds=[1, 2], history=3).load_sim_state(RacingTorchEnv(2, track_seeds=[1, 2]).sim_state())
    with pytest.raises(ValueError, match="history must be an integer"):
        RacingTorchEnv(1, track_seeds=1, history=65)
    with pytest.raises(ValueError, match="history_obs has shape"):  # refused before any car is touched
        RacingTorchEnv(2, track_seeds=[1, 2], history=5).load_sim_state(state)
    with pytest.raises(TypeError, match="privileged must be True or False"):
        RacingTorchEnv(1, track_seeds=1, privileged="no")
    RacingTorchEnv(2, track_seeds=[1, 2], history=3).sim_state()  # before the first reset too


def test_the_env_carries_the_history_in_both_collectors_bit_for_bit():
    from torchrl.envs import check_env_specs

    from racing.torchrl_env import RacingTorchEnv
    from tests.test_collectors import COMPARED, collect

    check_env_specs(RacingTorchEnv(3, track_seeds=[1, 2, 3], history=2, privileged=True))
    keys = [*COMPARED, ("history",), ("next", "history"), ("privileged",)]
    direct = collect("direct", steps=70, episodes=3, history=2, privileged=True)
    reference = collect("torchrl", steps=70, episodes=3, history=2, privileged=True)
    for ours, theirs in zip(direct, reference, strict=True):
        for key in keys:
            assert torch.equal(ours[key], theirs[key]), key


@pytest.mark.parametrize("algo", ["sac", "redq"])
def test_the_q_networks_read_the_true_state_and_the_history_and_the_actor_does_not(algo):
    _, learner = training(algo, "algo.td.privileged_critic=true")
    assert learner.networks.qvalue_nets[0].net.layers[0].weight.shape[-1] == 6 + 4 + 2
    assert learner.networks.qvalues[0].in_keys == ["observation", "privileged", "action"]
    assert learner.networks.actor_net[0].layers[0].weight.shape[-1] == 6
    assert "privileged" in learner.transition_keys and ("next", "privileged") in learner.transition_keys
    _, learner = training(algo, "algo.td.privileged_critic=true", "algo.td.critic_history=2")
    assert learner.networks.qvalue_nets[0].net.layers[0].weight.shape[-1] == 6 + 4 + 2 * (6 + 2) + 2
    assert learner.networks.qvalues[0].in_keys == ["observation", "privileged", "history", "action"]
    assert ("next", "history") in learner.transition_keys


@pytest.mark.slow
def test_privileged_members_equal_their_solo_runs_and_resume_exactly(tmp_path):
    assert_member_is_solo_and_resumes(tmp_path, ["algo=redq", "er=prioritised", *FAST, "episodes=5",
                                                 "algo.td.updates_per_step=0.1", "algo.redq.critics=3",
                                                 "algo.td.privileged_critic=true", "algo.td.critic_history=2", *BOTH])


@pytest.mark.parametrize("override, message", [
    (["algo=td3", "algo.td.privileged_critic=true"], "built for the losses redq, sac"),
    (["algo=tqc", "algo.td.critic_history=2"], "algo.td.critic_history is built for the losses redq, sac"),
    (["algo=sac", "algo.td.critic_history=65"], "critic_history must be at most 64"),
    (["algo=sac", "algo.td.critic_history=-1"], "critic_history must be >= 0"),
    (["algo=sac", "algo.td.critic_history=2", "algo.td.n_step=2"], "takes one-step transitions"),
    (["algo=sac", "algo.td.privileged_critic=true", "algo.td.n_step=3"], "takes one-step transitions"),
    (["algo=sac", "algo.td.privileged_critic=true", "compile=true"], "not supported with algo.td.privileged_critic"),
    (["algo=sac", "algo.sac.target_entropy_end=-4", "algo.sac.fixed_alpha=true"], "fixed_alpha: true there is none"),
    (["algo=sac", "algo.sac.target_entropy_end=1e9"], "within [-1e6, 1e6] nats"),
    (["algo=redq", "algo.sac.target_entropy=nan"], "target_entropy must be a finite number"),
    (["algo=redq", "algo.sac.target_entropy=-2e6"], "within [-1e6, 1e6] nats"),
    (["algo=sac", "algo.td.observation_norm=3"], "observation_norm must be"),
])
def test_bad_settings_are_refused_with_a_reason(override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        load(*override)


@pytest.mark.slow
def test_the_factor_table_pairs_each_configuration_with_the_base_by_track(tmp_path, capsys):
    from analysis.factors import factor_rows, main, t_interval

    run = ["algo=sac", "er=memory", *FAST, "episodes=2", f"seeds=[{A},{B}]"]
    train_population(load(*run), tmp_path / "sweep" / "base")
    train_population(load(*run, "gamma=0.95"), tmp_path / "sweep" / "gamma0.95")
    rows = factor_rows(tmp_path / "sweep", "base", oracle={A: 100.0, B: 200.0})
    assert [r["configuration"] for r in rows] == ["base", "gamma0.95"]
    finals = {name: [json.loads((tmp_path / "sweep" / name / f"seed{s}" / "summary.json").read_text())["final_mean"]
                     for s in sorted((A, B))] for name in ("base", "gamma0.95")}
    differences = [x - y for x, y in zip(finals["gamma0.95"], finals["base"])]
    mean = sum(differences) / 2
    half = 12.706 * abs(differences[0] - differences[1]) / math.sqrt(2) / math.sqrt(2)  # t(1) x sd / sqrt(n)
    assert rows[1]["vs base"] == round(mean, 2) and rows[1]["95% high"] == pytest.approx(mean + half, abs=0.01)
    assert t_interval([1.0, 2.0, 3.0]) == pytest.approx((2.0, 2.0 - 4.303 / math.sqrt(3), 2.0 + 4.303 / math.sqrt(3)))
    seeds = sorted((A, B))
    assert rows[0]["of the oracle"] == pytest.approx((finals["base"][0] / {A: 100.0, B: 200.0}[seeds[0]]
                                                      + finals["base"][1] / {A: 100.0, B: 200.0}[seeds[1]]) / 2, abs=1e-4)
    assert main([str(tmp_path / "sweep"), "--base", "base", "--table", str(tmp_path / "f.csv")]) == 0
    assert "| base |" in capsys.readouterr().out and (tmp_path / "f.csv").read_text().startswith("configuration,")
    train_population(load("algo=sac", "er=memory", *FAST, "episodes=2", f"seed={A}"), tmp_path / "sweep" / "one_track")
    assert main([str(tmp_path / "sweep"), "--base", "base"]) == 2
    assert "one_track has no run of track" in capsys.readouterr().err
    assert main([str(tmp_path / "sweep"), "--base", "nothing"]) == 2
    assert "no configuration 'nothing'" in capsys.readouterr().err
    assert main([str(tmp_path / "sweep" / "base" / f"seed{A}"), "--base", "base"]) == 2  # a run, not a sweep
    assert "is a run's folder, not a sweep's" in capsys.readouterr().err
    assert main([str(tmp_path / "sweep"), "--base", "base", "--markdown", str(tmp_path / "no" / "t.md")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    # a diverged run's final performance is no result: its configuration's row has no mean or difference
    (tmp_path / "sweep" / "one_track").rename(tmp_path / "elsewhere")
    train_population(load(*run, "algo.critic_lr=1e8", "algo.actor_lr=1e8", "algo.td.updates_per_step=1.0"),
                     tmp_path / "sweep" / "diverged")
    rows = {r["configuration"]: r for r in factor_rows(tmp_path / "sweep", "base", oracle={A: 100.0, B: 200.0})}
    assert rows["diverged"]["diverged"] >= 1 and rows["diverged"]["mean"] == "" and rows["diverged"]["vs base"] == ""
    assert "diverged" in [rows["diverged"][f"track {t}"] for t in sorted((A, B))]
