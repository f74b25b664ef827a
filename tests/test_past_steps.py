"""A policy that reads past steps (``env.past_steps=k``): every network reads the observation now, then the car's last k
observations and the k actions taken from them (``racing.history``).

Checked: the observation with past steps against the env's ``history`` entry (the one rule both follow) and its
spec; both collectors carry it bit for bit; a trained policy keeps its own history in a Gymnasium env and
acts there exactly as the run's acting policy did in training (across a respawn and a new episode, where
its history starts over); whole runs: a member equals its solo run and resumes exactly, the default leaves a
run's bits and its recorded settings alone, the saved actor evaluates as the run evaluated it (evaluate.py
and the benchmark's agent too), a run recorded under the key's old name (``env.memory``) still
evaluates and compares as the same run, and bad values are refused.
"""

import json
import re

import numpy as np
import pytest
import torch

from engine.config import ConfigError
from engine.evaluation import evaluate, load_policy, make_policy
from engine.runner import train_population
from learners.networks import member_state_dict
from learners.solo import GaussianPolicyNet, make_actor, make_policy as make_td_policy, make_sampler
from racing.history import History, past_size
from tests.test_config import load
from tests.test_few_samples import assert_member_is_solo_and_resumes
from tests.test_offpolicy import A, B, FAST, training
from tests.test_train import run_train


def test_the_with_past_is_the_observation_then_the_history():
    from torchrl.envs import check_env_specs

    from racing.torchrl_env import RacingTorchEnv

    assert past_size(6, 3) == 6 + 3 * 8
    remembering = RacingTorchEnv(2, track_seeds=[1, 2], past_steps=3, history=2)
    recording = RacingTorchEnv(2, track_seeds=[1, 2], history=3)
    assert remembering.observation_spec["observation"].shape == (2, 30)
    for env in (remembering, recording):
        env.set_seed(5)
    seen, reference = remembering.reset_tensors(), recording.reset_tensors()
    g = torch.Generator().manual_seed(0)
    for step in range(60):
        now, past = seen["observation"], reference["history"]
        assert torch.equal(now, torch.cat([reference["observation"], past], 1)), step
        assert torch.equal(seen["history"], torch.cat([past[:, :12], past[:, 18:22]], 1)), step  # the first 2 of 3
        action = torch.rand(2, 2, generator=g) * 2.4 - 1.2  # some beyond [-1, 1]: remembered clipped
        seen, reference = remembering.step_tensors(action), recording.step_tensors(action)
    assert remembering.sim.crashes.sum() > 0  # respawns happened: the history went on through them
    check_env_specs(RacingTorchEnv(3, track_seeds=[1, 2, 3], past_steps=2))


def _collect(backend: str):
    from collectors import make_collector
    from racing.torchrl_env import RacingTorchEnv

    torch.manual_seed(0)
    net = GaussianPolicyNet(past_size(6, 2), 2, [32])
    env = RacingTorchEnv(2, track_seeds=[A, A], past_steps=2)
    env.set_seed(7)
    collector = make_collector(backend, env, policy=make_td_policy(make_actor(net)), sample=make_sampler(net),
                               steps=70, episodes=4)
    return list(collector)


def test_both_collectors_carry_the_past_steps_bit_for_bit():
    direct, reference = _collect("direct"), _collect("torchrl")
    for ours, theirs in zip(direct, reference, strict=True):
        for key in ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done")):
            assert torch.equal(ours[key], theirs[key]), key
    batch = direct[2]  # episodes of 200 steps straddle the 70-step batches: the third batch starts over at 60
    start = batch["observation"][:, 60]
    assert torch.equal(start[:, 6:18], start[:, :6].repeat(1, 2)) and not start[:, 18:].any()


def _drive_in_training(learner, track: int, seed: int, steps: int) -> tuple[list, list]:
    """The run's acting policy without noise (a paused probe) in the TorchRL env of one car with past steps."""
    from racing.torchrl_env import RacingTorchEnv

    env = RacingTorchEnv(1, track_seeds=[track], past_steps=3)
    env.set_seed(seed)
    state, observations, actions = env.reset_tensors(), [], []
    with learner.sampler.paused():
        for _ in range(steps):
            action = learner.sampler(state["observation"])
            observations.append(state["observation"][0, :6].numpy())
            actions.append(action[0].numpy())
            state = env.step_tensors(action)
    return observations, actions


def test_a_policy_keeps_its_history_and_acts_as_the_run_acted_in_training():
    """Policy (the Gymnasium path of evaluate.py, score.py, the benchmark) against the acting policy in
    training: the same actions to the last bit over a whole episode with respawns and into a new one."""
    from racing.gym_env import RacingEnv

    cfg, learner = training("sac", "env.past_steps=3", seeds=(A,))
    with torch.no_grad():  # a policy that steers hard, so that the car leaves the track
        learner.networks.actor_net[0].layers[-1].bias[0, :2] = torch.tensor([1.0, 0.8])
    network = {"actor_hidden": list(cfg.network.actor_hidden), "activation": cfg.network.activation}
    policy = make_policy("sac", network, 6, member_state_dict(learner.networks.policy_net, 0), past_steps=3)
    env = RacingEnv(track_seed=A)
    for seed in (4, 5):  # a second episode: the history starts over
        expected_obs, expected = _drive_in_training(learner, A, seed, 200)
        observation, _ = env.reset(seed=seed)
        policy.reset()
        for step in range(200):
            assert np.array_equal(observation, expected_obs[step]), (seed, step)
            action = policy(observation)
            assert np.array_equal(action, expected[step]), (seed, step)
            observation, *_ = env.step(action)
        assert env.unwrapped.sim.crashes[0] > 0
    # without reset() the history of the last episode would carry over: other actions
    env.reset(seed=4)
    assert not np.array_equal(policy(env.reset(seed=4)[0]), _drive_in_training(learner, A, 4, 1)[1][0])


def test_the_history_refuses_to_act_before_it_has_seen_an_observation():
    history = History(1, 2, 6)
    with pytest.raises(RuntimeError, match="before its first observation"):
        history.act(np.zeros((1, 2)))


@pytest.mark.parametrize("algo", [pytest.param("sac", marks=pytest.mark.slow), "spg_p"])
def test_a_run_with_past_steps_evaluates_as_it_did_and_the_benchmark_resets_its_history(tmp_path, algo):
    from benchmark.protocol import load_agent, run_episode
    from racing.gym_env import RacingEnv

    er = "er=memory" if algo == "sac" else "er=hybrid"
    extra = ([*FAST[1:], "algo.td.updates_per_step=0.1"] if algo == "sac"
             else ["progress=false", "logger=none", "algo.minibatch_size=30"])
    result = run_train(f"algo={algo}", er, *extra, "episodes=3", "env.options.max_steps=60", f"seed={B}",
                       "eval_seeds=[1001]", "eval_episodes=2", "env.past_steps=2", f"hydra.run.dir={tmp_path / 'run'}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["settings"]["env"]["past_steps"] == 2
    policy, settings = load_policy(tmp_path / "run")
    assert policy.net is not None and policy.past_steps == 2
    scores = evaluate(policy, settings, [B, 1001], 2)
    assert scores[B] == summary["evaluation"]["own_track"] and scores[1001] == summary["evaluation"]["tracks"]["1001"]
    agent = load_agent(str(tmp_path / "run"))  # the benchmark's agent: the history starts over in each episode
    env = RacingEnv(track_seed=1001, max_steps=60)
    assert [run_episode(agent, env, seed) for seed in (0, 1)] == [run_episode(agent, env, seed) for seed in (0, 1)]
    assert run_episode(agent, env, 0) + run_episode(agent, env, 1) == pytest.approx(2 * scores[1001], abs=1e-9)

    # the same run as an older train.py recorded it (env.memory, sealed so): read with today's name
    from engine.config import RunConfig
    from engine.outputs import write_summary

    old = json.loads(json.dumps(summary))
    old["settings"]["env"] = {("memory" if k == "past_steps" else k): v for k, v in old["settings"]["env"].items()}
    write_summary(tmp_path / "run", old)
    assert "memory" in json.loads((tmp_path / "run" / "summary.json").read_text())["settings"]["env"]
    policy, _ = load_policy(tmp_path / "run")
    assert policy.past_steps == 2 and evaluate(policy, settings, [1001], 2)[1001] == scores[1001]
    assert RunConfig.same_run(old["settings"], summary["settings"])


@pytest.mark.slow
def test_members_equal_their_solo_runs_and_resume_exactly_with_past_steps(tmp_path):
    assert_member_is_solo_and_resumes(tmp_path, ["algo=sac", "er=prioritised", *FAST, "episodes=5",
                                                 "algo.td.updates_per_step=0.1", "env.past_steps=2",
                                                 "algo.td.critic_history=1"])


@pytest.mark.slow
def test_the_default_leaves_a_run_and_its_settings_alone(tmp_path):
    run = ["algo=sac", "er=memory", *FAST, "algo.td.updates_per_step=0.1", f"seed={A}"]
    train_population(load(*run), tmp_path / "plain")
    train_population(load(*run, "env.past_steps=0"), tmp_path / "zero")
    train_population(load(*run, "env.past_steps=1"), tmp_path / "one")
    plain = (tmp_path / "plain" / "metrics.csv").read_bytes()
    assert (tmp_path / "zero" / "metrics.csv").read_bytes() == plain
    assert (tmp_path / "one" / "metrics.csv").read_bytes() != plain
    from engine.config import RunConfig

    # recorded only when set: the settings of runs without past steps (older ones too) stay the same
    assert "past_steps" not in RunConfig.compose_mapping("algo=sac", "env.past_steps=0")["env"]
    assert RunConfig.compose_mapping("algo=sac", "env.past_steps=2")["env"]["past_steps"] == 2


@pytest.mark.parametrize("override, message", [
    ("env.past_steps=65", "env.past_steps must be an integer in [0, 64]"),
    ("env.past_steps=-1", "env.past_steps must be an integer in [0, 64]"),
    ("env.past_steps=1.5", "env.past_steps must be an integer"),
    ("env.past_steps=true", "env.past_steps must be an integer"),
    ("env.past_steps=false", "env.past_steps must be an integer"),
    ("env.past_steps=0.0", "env.past_steps must be an integer"),
])
def test_bad_past_steps_are_refused_with_a_reason(override, message):
    with pytest.raises(ConfigError, match=re.escape(message)):  # as train.py reads them (0.0 is not 0 steps)
        load("algo=sac", override)
