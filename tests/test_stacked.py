"""Stacked population networks: members are independent, and each equals a population of one."""

from __future__ import annotations

import pytest
import torch

from learners.solo import CriticNet, GaussianPolicyNet
from learners.optim import MemberAdam
from learners.networks import (StackedCriticNet, StackedGaussianPolicyNet, StackedLinear, load_member_state_dict,
                                member_state_dict, reset_parameters)

SEEDS = [2067791, 5468063, 5412436, 8273186]


def population(seeds):
    generators = [torch.Generator().manual_seed(s) for s in seeds]
    actor = reset_parameters(StackedGaussianPolicyNet(len(seeds), 6, 2, [100]), generators)
    critic = reset_parameters(StackedCriticNet(len(seeds), 8, [100, 100]), generators)
    return actor, critic


def data(seed, batch=200):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(batch, 6, generator=g), torch.rand(batch, 2, generator=g) * 2 - 1, torch.randn(batch, 1, generator=g)


def train_steps(actor, critic, batches, steps=20):
    """Adam steps on each member's own batch: losses are means per member, summed over members."""
    obs, act, ret = (torch.stack(parts) for parts in zip(*batches))
    critic_opt = MemberAdam(critic.parameters(), lr=5e-4)
    actor_opt = MemberAdam(actor.parameters(), lr=1e-3)
    for _ in range(steps):
        critic_loss = (ret - critic(obs, act)).pow(2).flatten(1).mean(1).sum()
        critic_opt.zero_grad()
        critic_loss.backward()
        critic_opt.step()
        loc, scale = actor(obs)
        actor_loss = -torch.distributions.Normal(loc, scale).log_prob(act).flatten(1).mean(1).sum()
        actor_opt.zero_grad()
        actor_loss.backward()
        actor_opt.step()


def test_initialisation_depends_on_the_member_seed_alone():
    actor, critic = population(SEEDS)
    for r, seed in enumerate(SEEDS):
        solo_actor, solo_critic = population([seed])
        for stacked, solo in ((actor, solo_actor), (critic, solo_critic)):
            for name, value in member_state_dict(stacked, r).items():
                assert torch.equal(value, member_state_dict(solo, 0)[name]), name
    assert not torch.equal(actor.loc_head.weight[0], actor.loc_head.weight[1])
    assert torch.count_nonzero(actor.body.layers[0].bias) == 0


def test_members_forward_like_the_solo_networks():
    """Saved member weights load into the solo networks (evaluate.py) and compute the same
    function, to float rounding (F.linear and bmm accumulate in other orders)."""
    torch.set_num_threads(1)
    actor, critic = population(SEEDS)
    obs = torch.rand(len(SEEDS), 3, 7, 6)  # extra batch dimensions, as SPG's candidates have
    act = torch.rand(len(SEEDS), 3, 7, 2)
    loc, scale = actor(obs)
    q = critic(obs, act)
    assert loc.shape == (4, 3, 7, 2) and q.shape == (4, 3, 7, 1)
    for r in range(len(SEEDS)):
        solo_actor, solo_critic = GaussianPolicyNet(6, 2, [100]), CriticNet(8, [100, 100])
        solo_actor.load_state_dict(member_state_dict(actor, r))
        solo_critic.load_state_dict(member_state_dict(critic, r))
        solo_loc, solo_scale = solo_actor(obs[r])
        torch.testing.assert_close((loc[r], scale[r]), (solo_loc, solo_scale), rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(q[r], solo_critic(obs[r], act[r]), rtol=1e-6, atol=1e-6)


def test_a_member_trains_exactly_like_a_population_of_one():
    """Twenty Adam steps of critic and actor on each member's own data: every member's weights
    equal those of the same member trained alone, to the bit."""
    torch.set_num_threads(1)
    actor, critic = population(SEEDS)
    train_steps(actor, critic, [data(s) for s in SEEDS])
    for r, seed in [(0, SEEDS[0]), (3, SEEDS[3])]:
        solo_actor, solo_critic = population([seed])
        train_steps(solo_actor, solo_critic, [data(seed)])
        for stacked, solo in ((actor, solo_actor), (critic, solo_critic)):
            for name, value in member_state_dict(stacked, r).items():
                assert torch.equal(value, member_state_dict(solo, 0)[name]), (r, name)


def test_order_of_members_does_not_matter():
    torch.set_num_threads(1)
    forward, backward = population(SEEDS), population(SEEDS[::-1])
    train_steps(*forward, [data(s) for s in SEEDS])
    train_steps(*backward, [data(s) for s in SEEDS[::-1]])
    last = len(SEEDS) - 1
    for a, b in zip(forward, backward):
        for name, value in member_state_dict(a, 0).items():
            assert torch.equal(value, member_state_dict(b, last)[name]), name


def test_a_diverging_member_leaves_the_others_alone():
    torch.set_num_threads(1)
    actor, critic = population(SEEDS[:2])
    batches = [data(SEEDS[0]), data(SEEDS[1])]
    batches[0] = (batches[0][0], batches[0][1], torch.full((200, 1), float("nan")))  # member 0's returns
    train_steps(actor, critic, batches)
    assert not torch.isfinite(critic.net.layers[0].weight[0]).all()
    alone = population(SEEDS[1:2])
    train_steps(*alone, batches[1:])
    for name, value in member_state_dict(critic, 1).items():
        assert torch.equal(value, member_state_dict(alone[1], 0)[name]), name


def test_member_weights_round_trip_and_bad_shapes_are_refused():
    actor, _ = population(SEEDS)
    other, _ = population([1, 2, 3, 4])
    load_member_state_dict(other, 2, member_state_dict(actor, 1))
    assert torch.equal(other.loc_head.weight[2], actor.loc_head.weight[1])
    with pytest.raises(ValueError, match="has 3 members on its first dimension, this layer 4"):
        actor(torch.rand(3, 6))
    with pytest.raises(ValueError, match="the weights have entries"):
        load_member_state_dict(other, 0, {"loc_head.weight": torch.zeros(2, 100)})


def test_exact_sqrt_is_the_correctly_rounded_root():
    """Against NumPy's float32 sqrt (the CPU's IEEE instruction), over normal and subnormal numbers:
    the kernels' every path this CPU runs (scalar, AVX2, AVX-512) and the float64 fallback."""
    import numpy as np

    from learners import kernels
    from learners.optim import exact_sqrt, wide_sqrt

    g = torch.Generator().manual_seed(0)
    x = torch.rand(1_000_003, generator=g) * 10
    x[::7] *= 1e-20
    x[::11] = torch.rand(x[::11].shape, generator=g) * 1e-40  # subnormal
    x[::13] = 0.0
    x[-5:] = torch.tensor([1e-45, 3.4e38, 2.0, 1e-38, 0.25])  # in the scalar tail of the vector paths
    expected = np.sqrt(x.numpy())
    roots = [wide_sqrt([x])[0]]
    if kernels.unavailable_reason() is None:
        roots += [exact_sqrt([x], isa)[0] for isa in kernels.isas()]
        roots += [exact_sqrt([x[1:]])[0], exact_sqrt([x.view(1000003, 1).t()])[0]]  # offset; non-contiguous
        expected_shifted = expected[1:]
    for root in roots:
        assert root.dtype == torch.float32
        want = expected_shifted if root.numel() == x.numel() - 1 else expected
        assert np.array_equal(root.numpy().ravel(), want)


@pytest.mark.parametrize("weight_decay", [0.0, 0.05])
def test_member_adam_is_torch_adam_with_a_correctly_rounded_sqrt_and_restores(monkeypatch, weight_decay):
    """... and with weight decay, torch's AdamW (decoupled decay; AdamW at 0 is Adam)."""
    from learners.optim import exact_sqrt

    torch.set_num_threads(1)
    monkeypatch.setattr(torch, "_foreach_sqrt", exact_sqrt)  # torch's Adam, its root correctly rounded
    nets = [population(SEEDS)[1] for _ in range(3)]
    obs, act, ret = (torch.stack(parts) for parts in zip(*[data(s) for s in SEEDS]))
    ours = MemberAdam(nets[0].parameters(), lr=5e-4, weight_decay=weight_decay)
    theirs = torch.optim.AdamW(nets[1].parameters(), lr=5e-4, weight_decay=weight_decay, foreach=True)
    for step in range(12):
        for net, opt in ((nets[0], ours), (nets[1], theirs)):
            opt.zero_grad()
            (ret - net(obs, act)).pow(2).flatten(1).mean(1).sum().backward()
            opt.step()
        if step == 5:  # a copy restored from the state at step 6 goes on identically
            restored = MemberAdam(nets[2].parameters(), lr=5e-4, weight_decay=weight_decay)
            nets[2].load_state_dict(nets[0].state_dict())
            restored.load_state_dict(ours.state_dict())
        elif step > 5:
            restored.zero_grad()
            (ret - nets[2](obs, act)).pow(2).flatten(1).mean(1).sum().backward()
            restored.step()
    for a, b, c in zip(nets[0].parameters(), nets[1].parameters(), nets[2].parameters()):
        assert torch.equal(a, b) and torch.equal(a, c)
    with pytest.raises(ValueError, match="optimiser state exp_avg has shapes"):
        MemberAdam(population(SEEDS[:2])[1].parameters(), lr=1e-3).load_state_dict(ours.state_dict())


@pytest.mark.parametrize("members", [1, 3])
@pytest.mark.parametrize("shape", [(), (5,), (2, 9)])
@pytest.mark.parametrize("hidden", [[100], [24, 40]])
def test_the_acting_call_is_the_forward_pass_bit_for_bit(members, shape, hidden):
    """``act`` (the sampler's call per environment step: no module calls, the padded rows as
    ``forward`` pads them) gives ``forward``'s values bit for bit, with the project's products and
    without them (then it is ``forward``), and after its parameters are replaced; and ``fast_tanh``
    without a graph gives the values it gives with one."""
    from learners import kernels
    from learners.networks import fast_tanh

    generators = [torch.Generator().manual_seed(s) for s in SEEDS[:members]]
    net = reset_parameters(StackedGaussianPolicyNet(members, 6, 2, hidden), generators)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(torch.rand(p.shape, generator=generators[0]) * 0.3)  # biases away from zero
    obs = torch.rand(members, *shape, 6, generator=generators[0]) * 4 - 2
    previous = kernels.active()
    try:
        for fma in (True, False):
            if kernels.use(fma) and fma:
                pytest.skip("the kernels cannot be built here")
            with torch.no_grad():
                expected = net(obs)
            got = net.act(obs)
            assert all(torch.equal(a, b) for a, b in zip(expected, got))
            assert got[0].shape == (members, *shape, 2)
    finally:
        kernels.use(previous)
    net.act(obs)
    net.scale_head.weight = torch.nn.Parameter(net.scale_head.weight.detach() * 0.5)  # a later layer's, replaced
    with torch.no_grad():
        expected = net(obs)
    assert all(torch.equal(a, b) for a, b in zip(expected, net.act(obs))) and not torch.equal(got[1], expected[1])
    net.loc_head = StackedLinear(members, hidden[-1], 2)  # a layer replaced
    with torch.no_grad():
        net.loc_head.weight.copy_(torch.rand(net.loc_head.weight.shape, generator=generators[0]))
        expected = net(obs)
    assert all(torch.equal(a, b) for a, b in zip(expected, net.act(obs)))
    x = torch.randn(members, 64, 100, generator=generators[0]) * 3
    with torch.no_grad():
        plain = fast_tanh(x)
    assert torch.equal(plain, fast_tanh(x.clone().requires_grad_()).detach())
