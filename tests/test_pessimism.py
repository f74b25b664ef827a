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
