"""algo.td.pessimism: how SAC's target and actor combine the Q-networks (losses.td.q_reduce), against
hand-computed values."""

import pytest
import torch

from losses.td import ACTION_NOISE_KEY, q_reduce
from tests.test_offpolicy import A, B, training, transitions


def test_q_reduce_is_the_minimum_the_mean_or_an_optimistic_value():
    values = torch.tensor([[1.0, -2.0, 5.0], [3.0, -2.0, 4.0]])  # two Q-networks, three transitions
    assert torch.equal(q_reduce(values, None), torch.tensor([1.0, -2.0, 4.0]))
    assert torch.equal(q_reduce(values, 0.0), torch.tensor([2.0, -2.0, 4.5]))
    # two networks: std is half their distance, so pessimism 1 gives the minimum, -0.5 the mean plus a quarter
    assert torch.allclose(q_reduce(values, 1.0), torch.tensor([1.0, -2.0, 4.0]), atol=1e-6)
    assert torch.allclose(q_reduce(values, -0.5), torch.tensor([2.5, -2.0, 4.75]), atol=1e-6)
    three = torch.tensor([[0.0], [3.0], [6.0]])  # population std sqrt(6)
    assert torch.allclose(q_reduce(three, 2.0), torch.tensor([3.0 - 2.0 * 6.0 ** 0.5]))


def test_the_gradient_stays_finite_where_the_networks_agree():
    values = torch.tensor([[2.0, 1.0], [2.0, 3.0]], requires_grad=True)
    q_reduce(values, 1.0).sum().backward()
    assert torch.isfinite(values.grad).all()
    assert torch.allclose(values.grad[:, 1], torch.tensor([1.0, 0.0]))  # the minimum's gradient where they differ


@pytest.mark.parametrize("pessimism", [0.0, -0.5])
def test_the_target_and_the_actor_read_the_combined_values(pessimism):
    """The loss module's target is r + gamma * (mean - beta * std of the target Q-networks at (s', a') - alpha *
    log pi(a'|s')), and its actor loss alpha * log pi(a|s) - (mean - beta * std of the Q-networks at (s, a)), both
    computed here by hand from the networks and the drawn noise."""
    cfg, t = training("sac", f"algo.td.pessimism={pessimism}", seeds=(A, B))
    loss = t.loss
    data = transitions(2, 32)
    loss.draw(data)
    out = loss(data.clone())
    actor_net, critic = t.networks.actor_net, loss.qvalue_network.module

    def sample(observation, noise):
        loc, scale = actor_net(observation)
        pre = loc + noise * scale
        action = torch.tanh(pre)
        log_prob = (torch.distributions.Normal(loc, scale).log_prob(pre) - torch.log1p(-action.pow(2))).sum(-1)
        return action, log_prob

    def values(params, observation, action):
        out = []
        for q in range(params.shape[0]):
            with params[q].to_module(loss.qvalue_network):
                out.append(critic(torch.cat([observation, action], -1)).squeeze(-1))
        return torch.stack(out)

    def combined(v):
        return v.mean(0) - pessimism * v.std(0, correction=0)

    alpha = loss.log_alpha.exp().detach().unsqueeze(-1)
    with torch.no_grad():
        nxt = data["next"]
        next_action, next_log_prob = sample(nxt["observation"], nxt[ACTION_NOISE_KEY])
        target = nxt["reward"].squeeze(-1) + cfg.gamma * (
            combined(values(loss.target_qvalue_network_params, nxt["observation"], next_action)) - alpha * next_log_prob)
        predicted = values(loss.qvalue_network_params, data["observation"], data["action"])
        action, log_prob = sample(data["observation"], data[ACTION_NOISE_KEY])
        actor = alpha * log_prob - combined(values(loss.qvalue_network_params, data["observation"], action))
    assert torch.allclose(out["loss_qvalue"], ((predicted - target) ** 2).sum(0), rtol=1e-4, atol=1e-4)
    assert torch.allclose(out["loss_actor"], actor, rtol=1e-4, atol=1e-4)


# ------------------------------------------------------------------ python -m analysis.pessimism
from tests.test_driving import run  # noqa: E402,F401  (a tiny finished SAC run on track 1001, 30-step episodes)


def test_the_critics_are_the_run_s_q_networks(run):
    """Each row of the stacked network load_critics builds computes one of the run's Q-networks, here by hand
    from critic.pt's weights (tanh MLP)."""
    from analysis.pessimism import load_critics
    from engine.checkpoint import load_tensors
    from engine.evaluation import load_policy

    _, settings = load_policy(run)
    critics = load_critics(run, settings)
    state = load_tensors(run / "critic.pt", "critic")
    x = torch.rand(7, 8, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        stacked = critics(x.expand(2, 7, 8))
    for q in range(2):
        h = x
        for i in range(3):
            h = h @ state[f"module.net.layers.{i}.weight"][q].T + state[f"module.net.layers.{i}.bias"][q]
            h = torch.tanh(h) if i < 2 else h
        assert torch.allclose(stacked[q], h, atol=1e-5)


def test_a_true_return_is_the_discounted_sum_of_one_car_s_rewards(run):
    """discounted_returns for the oracle's states equals driving a copy of each car alone, step by step."""
    import numpy as np

    from analysis.pessimism import discounted_returns, oracle_line
    from engine.evaluation import load_policy, make_env
    from racing.oracle import Oracle
    from racing.sim import RacingSim

    policy, settings = load_policy(run)
    env = make_env(settings, 1001)
    line = oracle_line(env, 1, 0, policy)
    assert len(line["cars"]) == 30 and line["observations"].shape == (30, 6)
    sim = env.unwrapped.sim
    batched = discounted_returns(sim, line, line["oracle"], policy, 0.9, 10)
    for i in (0, 17, 29):
        car = RacingSim(1, None, sim.config, track=sim.tracks[0])
        car.seed(0)
        car.reset()
        for name in Oracle.STATE:
            getattr(car, name)[:] = line["cars"][i][name]
        car.t[:] = 0
        total, action = 0.0, line["oracle"][i]
        for step in range(10):
            reward, terminated, truncated, _ = car.step(np.array([action[0]]), np.array([action[1]]))
            total += 0.9 ** step * float(reward[0])
            if terminated[0] or truncated[0]:
                break
            action = policy(car.observe()[0])
        assert batched[i] == pytest.approx(total, abs=1e-9)


def test_along_the_policy_s_own_line_its_own_action_s_true_return_is_its_episode_s(run):
    """--line policy: the states are the policy's own episode's, so taking its own action there and following it
    drives that episode on: the discounted return equals the episode's own rewards from that step; --compare
    slower/faster moves only the throttle, by delta, within [-1, 1]."""
    import numpy as np

    from analysis.pessimism import compared_actions, discounted_returns, policy_line
    from engine.evaluation import drive_episode, load_policy, make_env

    policy, settings = load_policy(run)
    env = make_env(settings, 1001)
    rewards = []
    original = env.step

    def step(action):
        out = original(action)
        rewards.append(float(out[1]))
        return out

    env.step = step
    drive_episode(lambda e, o: policy(o), env, 0, reset=policy.reset)
    del env.step
    line = policy_line(env, 1, 0, policy)
    own = policy.actions(torch.as_tensor(line["observations"]))
    assert np.array_equal(line["oracle"], own.numpy()) and len(line["cars"]) == len(rewards) == 30
    returns = discounted_returns(env.unwrapped.sim, line, own.double().numpy(), policy, 0.9, 10)
    for i in (0, 11, 20):
        assert returns[i] == pytest.approx(sum(0.9 ** j * rewards[i + j] for j in range(10)), abs=1e-9)
    own = torch.tensor([[0.95, 0.3], [-0.95, -0.2], [0.0, 1.0]])
    slower, faster = compared_actions(own, line, "slower", 0.1), compared_actions(own, line, "faster", 0.1)
    assert torch.allclose(slower, torch.tensor([[0.85, 0.3], [-1.0, -0.2], [-0.1, 1.0]]))
    assert torch.allclose(faster, torch.tensor([[1.0, 0.3], [-0.85, -0.2], [0.1, 1.0]]))


@pytest.mark.slow
def test_the_table_holds_a_row_per_run_and_bad_input_is_one_line(run, tmp_path, capsys):
    import csv

    from analysis import pessimism

    assert pessimism.main([str(run), "--episodes", "1", "--horizon", "10", "--table", str(tmp_path / "p.csv")]) == 0
    with open(tmp_path / "p.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 1 and rows[0]["loss"] == "sac" and rows[0]["states"] == "30"
    assert 0 <= float(rows[0]["misranked"]) <= 1 and float(rows[0]["spread_oracle"]) >= 0
    assert "| critic_gap_min |" in capsys.readouterr().out
    assert pessimism.main([str(run), "--horizon", "30"]) == 2  # no shorter than the run's 30-step episodes
    assert "--horizon must be below the episode's 30 steps" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        pessimism.main([str(run), "--episodes", "0"])
    assert "argument --episodes: must be in [1, 100], got" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        pessimism.main([str(run), "--line", "policy"])  # its own actions against themselves: nothing to compare
    assert "--line policy scores the policy's own actions; compare them with --compare slower or faster" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit):
        pessimism.main([str(run), "--episodes", "2", "--seed", str(2**32 - 1)])
    assert "--seed must be in [0, 2**32 - --episodes]" in capsys.readouterr().err
    for bad, said in (("0", "--delta must be a throttle change in (0, 2]"), ("nan", "argument --delta: must be a finite"),
                      ("3", "argument --delta: must be a finite number in [0, 2], got 3")):
        with pytest.raises(SystemExit):
            pessimism.main([str(run), "--compare", "slower", "--delta", bad])
        assert said in capsys.readouterr().err
    assert pessimism.main([str(run), "--episodes", "1", "--horizon", "10", "--line", "policy", "--compare", "slower",
                           "--table", str(tmp_path / "s.csv")]) == 0
    with open(tmp_path / "s.csv", newline="") as f:
        [row] = list(csv.DictReader(f))
    assert row["states"] == "30" and 0 <= float(row["misled"]) <= 1
    from tests.test_readme import readme_commands

    for args in readme_commands("-m analysis.pessimism"):  # the documented lines, on the tiny run
        args = [str(run) if a.startswith("outputs/") else a for a in args]
        assert pessimism.main([*args, "--episodes", "1", "--horizon", "10"]) == 0, args


def test_a_run_it_cannot_read_is_named_and_skipped_and_the_others_measured(run, tmp_path, capsys):
    """A SimbaV2 run's critic (of normalised observations) beside a SAC run: one line naming it, the SAC run's row written,
    exit 2 (something was skipped); a run given twice is measured once."""
    import csv

    from analysis import pessimism
    from engine.config import RunConfig
    from engine.runner import train_population

    other = tmp_path / "simbav2"
    settings = RunConfig.compose_mapping("algo=simbav2", "er=memory", "episodes=2", "algo.td.warmup_episodes=1",
                                         "algo.td.updates_per_step=0.1", "env.options.max_steps=30",
                                         "er.buffer_size=300", "algo.minibatch_size=16", "seed=1001",
                                         "progress=false", "logger=none")
    train_population(RunConfig.from_mapping(settings), other, settings)
    table = tmp_path / "p.csv"
    assert pessimism.main([str(other), str(run), str(run), "--episodes", "1", "--horizon", "5",
                           "--table", str(table)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "its critics read normalised observations" in err[0] and str(other) in err[0]
    with open(table, newline="") as f:
        assert [r["run"] for r in csv.DictReader(f)] == [str(run)]


@pytest.mark.slow
def test_critics_of_normalised_observations_are_skipped_in_one_line(tmp_path, capsys):
    from analysis import pessimism
    from tests.test_start import train

    normed = tmp_path / "normed"
    train(normed, "algo=sac", "er=memory", "episodes=2", "algo.td.warmup_episodes=1", "algo.td.updates_per_step=0.1",
          "env.options.max_steps=30", "seed=1001", "progress=false", "logger=none", "algo.td.observation_norm=true")
    assert pessimism.main([str(normed), "--episodes", "1", "--horizon", "5"]) == 2
    assert "its critics read normalised observations" in capsys.readouterr().err


def test_an_output_inside_a_run_folder_is_refused_before_any_work(run, capsys):
    from analysis import pessimism

    with pytest.raises(SystemExit):
        pessimism.main([str(run), "--table", str(run / "summary.json")])
    assert "is inside the run folder" in capsys.readouterr().err
    assert (run / "summary.json").read_text().startswith("{")
