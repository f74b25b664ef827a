"""The data path: both collector backends, Monte-Carlo returns, replay memory."""

import pytest
import torch
from tensordict import TensorDict

from collectors import (DirectCollector, ReplayMemory, ReplaySchedule, add_monte_carlo_returns,
                        episode_transitions, make_collector, sample_minibatch)
from learners.solo import GaussianPolicyNet, make_actor, make_policy, make_sampler
from racing.torchrl_env import RacingTorchEnv

COMPARED = [("observation",), ("action",), ("done",), ("next", "observation"), ("next", "reward"),
            ("next", "done"), ("next", "terminated"), ("next", "truncated"), ("next", "crashed")]


def collect(backend, cars=2, episodes=2, steps=200, **env_kwargs):
    torch.manual_seed(0)
    net = GaussianPolicyNet(6, 2, [100])
    env = RacingTorchEnv(cars, track_seeds=[2067791] * cars, **env_kwargs)
    env.set_seed(7)
    collector = make_collector(backend, env, policy=make_policy(make_actor(net)), sample=make_sampler(net),
                               steps=steps, episodes=episodes)
    batches = list(collector)
    collector.shutdown()
    return batches


@pytest.mark.parametrize("steps", [200, 70])
def test_direct_collector_reproduces_torchrl_collector(steps):
    """Same seeds, same episodes: every observation, action, reward and flag, bit for bit.

    With 70-frame batches, episodes straddle batches and cars reset mid-batch."""
    direct = collect("direct", steps=steps, episodes=3)
    reference = collect("torchrl", steps=steps, episodes=3)
    assert len(direct) == len(reference) == 3
    for ours, theirs in zip(direct, reference):
        assert ours.batch_size == theirs.batch_size == torch.Size([2, steps])
        for key in COMPARED:
            assert torch.equal(ours[key], theirs[key]), key


def test_one_batch_is_one_episode_per_car():
    (batch,) = collect("direct", episodes=1)
    done = batch["next", "done"].squeeze(-1)
    assert done[:, -1].all() and done.sum() == 2
    assert batch["next", "truncated"][:, -1].all() and not batch["next", "terminated"].any()
    assert (batch["action"].abs() <= 1).all()


def test_monte_carlo_returns_match_a_plain_loop():
    (batch,) = collect("direct", cars=1, episodes=1, steps=200)
    add_monte_carlo_returns(batch, 0.9)
    rewards = batch["next", "reward"][0, :, 0].double().tolist()
    expected, g = [], 0.0
    for r in reversed(rewards):
        g = r + 0.9 * g
        expected.append(g)
    expected.reverse()
    assert torch.allclose(batch["value_target"][0, :, 0].double(), torch.tensor(expected, dtype=torch.float64),
                          atol=1e-4)


def test_returns_stop_at_episode_ends():
    reward = torch.ones(1, 6, 1)
    done = torch.tensor([False, False, True, False, False, True]).reshape(1, 6, 1)
    batch = TensorDict({"next": {"reward": reward, "done": done}}, batch_size=[1, 6])
    add_monte_carlo_returns(batch, 0.5)
    assert batch["value_target"].flatten().tolist() == [1.75, 1.5, 1.0, 1.75, 1.5, 1.0]


def test_replay_memory_overwrites_the_oldest():
    memory = ReplayMemory(capacity=5)
    for start in (0, 3):
        memory.add(TensorDict({"x": torch.arange(start, start + 3.0)}, batch_size=[3]))
    assert len(memory) == 5
    assert sorted(memory.contents()["x"].tolist()) == [1.0, 2.0, 3.0, 4.0, 5.0]


def test_minibatches_are_drawn_with_replacement():
    data = TensorDict({"x": torch.arange(3.0)}, batch_size=[3])
    torch.manual_seed(0)
    mb = sample_minibatch(data, 50)
    assert mb.batch_size == torch.Size([50]) and set(mb["x"].tolist()) == {0.0, 1.0, 2.0}


def test_transitions_flatten_cars_and_time():
    (batch,) = collect("direct", cars=2, episodes=1)
    add_monte_carlo_returns(batch, 0.9)
    flat = episode_transitions(batch)
    assert flat.batch_size == torch.Size([400]) and set(flat.keys()) == {"observation", "action", "value_target"}


def test_hybrid_schedule_halves_minibatches():
    assert ReplaySchedule("hybrid", True, True, 0.5).minibatch_size(200) == 100
    assert ReplaySchedule("recent", False, True, 1.0).minibatch_size(200) == 200


def test_unknown_backend_names_the_choices():
    env = RacingTorchEnv(1, track_seeds=[1])
    with pytest.raises(ValueError, match="must be one of"):
        make_collector("fast", env, steps=200, episodes=1)


def test_direct_collector_checks_actions():
    env = RacingTorchEnv(1, track_seeds=[1])
    collector = DirectCollector(env, lambda obs: torch.full((1, 2), float("nan")), steps=5, total_frames=5)
    with pytest.raises(ValueError, match="NaN"):
        collector.collect()
