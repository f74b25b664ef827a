"""Trust-PCL (losses/trust_pcl.py): the path consistency over sub-episodes (episode ends inside them
included), the relative entropy to the lagged policy, the trust region's coefficient, the losses'
gradients against the consistency's square, the sub-episode sampler, and the learner in the pipeline."""

import math

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import TanhNormal
from torchrl.objectives import SoftUpdate

from collectors.replay import sample_sub_episodes
from engine.config import ConfigError
from engine.evaluation import make_policy
from engine.runner import train_population
from learners.td.trust_pcl import recent_returns
from losses.trust_pcl import (TrustPCLLoss, discounted_sums, path_consistency, relative_entropy_coefficient,
                              trajectory_divergence)
from tests.test_config import load
from tests.test_offpolicy import A, FAST, solo_and_resumed_pair, training

F64 = torch.float64


# -------------------------------------------------------------------- the consistency
def test_the_consistency_of_a_sub_episode_is_the_hand_computed_sum():
    gamma, tau, lam = 0.9, 0.1, 2.0
    rewards = torch.tensor([1.0, 0.5, 2.0], dtype=F64)
    log_probs = torch.tensor([-1.0, -0.5, -2.0], dtype=F64)
    lagged = torch.tensor([-1.2, -0.4, -1.0], dtype=F64)
    value, final = torch.tensor(3.0, dtype=F64), torch.tensor(4.0, dtype=F64)
    full = torch.tensor([True, True, True])
    terms = [r - (tau + lam) * lp + lam * lg for r, lp, lg in zip(rewards.tolist(), log_probs.tolist(), lagged.tolist())]
    hand = -3.0 + gamma ** 3 * 4.0 + terms[0] + gamma * terms[1] + gamma ** 2 * terms[2]
    c = path_consistency(value, final, rewards, log_probs, lagged, full, gamma, tau, torch.tensor(lam, dtype=F64))
    assert c.item() == pytest.approx(hand, rel=1e-14)
    # the episode ends after two steps: the third is not part of it, and the final value is discounted twice
    cut = torch.tensor([True, True, False])
    hand = -3.0 + gamma ** 2 * 4.0 + terms[0] + gamma * terms[1]
    c = path_consistency(value, final, rewards, log_probs, lagged, cut, gamma, tau, torch.tensor(lam, dtype=F64))
    assert c.item() == pytest.approx(hand, rel=1e-14)
    # whatever lies past the end (here NaN) takes no part
    poisoned = torch.tensor([1.0, 0.5, math.nan], dtype=F64)
    assert discounted_sums(poisoned, cut, gamma).item() == pytest.approx(1.0 + gamma * 0.5, rel=1e-14)


def test_the_trust_regions_divergence_and_its_coefficient_are_the_hand_computed_ones():
    # returns (0, 1) at lambda 1: p = (1, e) / (1 + e); KL = E_p[R] - log mean exp(R)
    e = math.e
    assert trajectory_divergence([0.0, 1.0], 1.0) == pytest.approx(e / (1 + e) - math.log((1 + e) / 2), rel=1e-14)
    assert trajectory_divergence([5.0, 5.0, 5.0], 0.3) == pytest.approx(0.0, abs=1e-15)  # equal returns: no divergence
    returns = [float(r) for r in np.random.default_rng(0).normal(100, 20, 20)]
    kl = [trajectory_divergence(returns, lam) for lam in (1.0, 10.0, 100.0, 1000.0)]
    assert kl == sorted(kl, reverse=True)  # a larger coefficient, a smaller divergence
    lam = relative_entropy_coefficient(returns, 0.001, 200)
    assert 0 < lam < 1000
    bracket = 1000 / 2 ** 14  # the bisection's final bracket
    assert trajectory_divergence(returns, lam - bracket) >= 0.2 >= trajectory_divergence(returns, lam + bracket)
    assert relative_entropy_coefficient(returns[:8], 0.001, 200) == 500.0  # too few episodes: the bracket's middle
    assert relative_entropy_coefficient([1e6] + returns, 0.001, 200) > 0  # large returns do not overflow


# ---------------------------------------------------------------------------- the loss
class _Linear(nn.Module):
    def __init__(self, inputs, outputs, seed, gaussian=False):
        super().__init__()
        g = torch.Generator().manual_seed(seed)
        self.weight = nn.Parameter(torch.randn(outputs, inputs, generator=g, dtype=F64) * 0.3)
        self.bias = nn.Parameter(torch.randn(outputs, generator=g, dtype=F64) * 0.3)
        self.gaussian = gaussian

    def forward(self, x):
        out = x @ self.weight.T + self.bias
        if self.gaussian:
            loc, scale = out.chunk(2, -1)
            return loc, nn.functional.softplus(scale) + 0.1
        return out


def _pcl_loss(**kwargs):
    actor = TensorDictModule(_Linear(6, 4, 1, gaussian=True), ["observation"], ["loc", "scale"])
    value = TensorDictModule(_Linear(6, 1, 2), ["observation"], ["state_value"])
    loss = TrustPCLLoss(actor, value, **{"gamma": 0.9, "rollout": 3, **kwargs})
    SoftUpdate(loss, tau=0.5)
    with torch.no_grad():  # the lagged networks differ from the online ones
        for params in (loss.target_actor_network_params, loss.target_value_network_params):
            params.apply_(lambda p: p.add_(0.05))
    return loss


def _sub_episodes(n=4, d=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict({
        "observation": torch.rand(n, d, 6, generator=g, dtype=F64),
        "action": torch.rand(n, d, 2, generator=g, dtype=F64) * 1.8 - 0.9,
        "mask": torch.tensor([[True, True, True], [True, True, False], [True, False, False], [True, True, True]]),
        "next": TensorDict({"observation": torch.rand(n, d, 6, generator=g, dtype=F64),
                            "reward": torch.rand(n, d, 1, generator=g, dtype=F64),
                            "terminated": torch.tensor([[False], [False], [False], [False], [True], [False],
                                                        [False], [False], [False], [False], [False], [True]]
                                                       ).reshape(n, d, 1)}, batch_size=[n, d]),
    }, batch_size=[n, d])


def test_the_loss_computes_each_sub_episodes_consistency_with_the_lagged_policy_and_value():
    loss = _pcl_loss(entropy=0.1, coefficient=2.0, clip=None)
    data = _sub_episodes()
    out = loss(data)
    actor, value = loss.actor_network.module, loss.value_network.module
    with torch.no_grad():
        lagged_actor = _Linear(6, 4, 1, gaussian=True)
        lagged_value = _Linear(6, 1, 2)
        for net, params in ((lagged_actor, loss.target_actor_network_params),
                            (lagged_value, loss.target_value_network_params)):
            net.weight.copy_(params["module", "weight"])
            net.bias.copy_(params["module", "bias"])
        for i, length in enumerate([3, 2, 1, 3]):
            s, a = data["observation"][i], data["action"][i]
            pi, lagged = TanhNormal(*actor(s), low=-1.0, high=1.0), TanhNormal(*lagged_actor(s), low=-1.0, high=1.0)
            lp, lg = pi.log_prob(a), lagged.log_prob(a)
            r = data["next", "reward"][i, :, 0]
            final = 0.0 if data["next", "terminated"][i, length - 1, 0] else lagged_value(
                data["next", "observation"][i, length - 1]).item()
            hand = -value(s[0]).item() + 0.9 ** length * final + sum(
                0.9 ** k * (r[k] - 2.1 * lp[k] + 2.0 * lg[k]).item() for k in range(length))
            assert out["consistency"][i].item() == pytest.approx(hand, rel=1e-12), i
    assert data["next", "terminated"][1, 1, 0]  # sub-episode 1 ends at its episode's terminal step: final value 0


@pytest.mark.parametrize("clip", [None, 0.05])
def test_the_gradients_are_those_of_the_consistencys_square_the_policys_divided_by_its_coefficient(clip):
    """The value network descends 1/2 C^2 (through V(s_t)); the policy descends 1/2 C^2 / (tau + lambda),
    the authors' update; with C clipped, C stands at the clip in both."""
    tau, lam = 0.1, 2.0
    loss = _pcl_loss(entropy=tau, coefficient=lam, clip=clip)
    data = _sub_episodes()
    params = list(loss.actor_network.parameters()) + list(loss.value_network.parameters())

    def grads(objective):
        for p in params:
            p.grad = None
        objective.backward()
        return [p.grad.clone() for p in params]

    out = loss(data)
    ours = grads((out["loss_actor"] + out["loss_value"]).sum())
    # 1/2 C^2 with every gradient path of C (the lagged networks' parts have none)
    observation, action, mask = data["observation"], data["action"], data["mask"]
    log_probs = loss.log_prob(observation, action)
    with torch.no_grad():
        lagged = loss.log_prob(observation, action, lagged=True)
    value = loss.value_network.module(observation[:, 0]).squeeze(-1)
    final = (out["consistency"] - path_consistency(value, torch.zeros_like(value), data["next", "reward"][..., 0],
                                                   log_probs, lagged, mask, 0.9, tau, torch.tensor(lam))).detach()
    c = path_consistency(value, torch.zeros_like(value), data["next", "reward"][..., 0], log_probs, lagged, mask, 0.9,
                         tau, torch.tensor(lam, dtype=F64)) + final
    torch.testing.assert_close(c.detach(), out["consistency"], rtol=1e-12, atol=1e-12)
    held = c.detach() if clip is None else c.detach().clamp(-clip, clip)
    # d/dtheta 1/2 C^2 = C dC/dtheta, with C replaced by its clipped value
    square = grads((held * c).sum())
    n_actor = len(list(loss.actor_network.parameters()))
    for mine, reference in zip(ours[:n_actor], square[:n_actor]):
        torch.testing.assert_close(mine * (tau + lam), reference, rtol=1e-10, atol=1e-12)
    for mine, reference in zip(ours[n_actor:], square[n_actor:]):
        torch.testing.assert_close(mine, reference, rtol=1e-10, atol=1e-12)
    if clip is not None:
        assert out["consistency"].abs().max() > clip  # the clip was in force


def test_lambda_moves_one_percent_of_the_way_per_step_and_is_saved_with_the_loss():
    loss = _pcl_loss(coefficient=10.0)
    loss.move_coefficient(torch.tensor([110.0], dtype=F64))
    assert loss.coefficient.item() == pytest.approx(11.0, rel=1e-15)
    assert torch.equal(loss.state_dict()["coefficient"], loss.coefficient)


# ------------------------------------------------------------------------- sub-episodes
def test_sub_episodes_are_consecutive_steps_of_one_episode_from_each_members_generator():
    steps, members, n = 5, 2, 20  # four episodes of five steps per member
    slot = torch.arange(n).repeat(members, 1)
    data = TensorDict({"slot": slot, "member": torch.arange(members).unsqueeze(1).expand(members, n)},
                      batch_size=[members, n])
    gens = [torch.Generator().manual_seed(s) for s in (1, 2)]
    batch = sample_sub_episodes(data, 500, 3, steps, gens)
    assert batch.batch_size == (members, 500, 3)
    first, mask = batch["slot"][..., 0], batch["mask"]
    for k in range(3):
        inside = (first % steps) + k < steps
        assert torch.equal(mask[..., k], inside)
        assert torch.equal(batch["slot"][..., k][inside], (first + k)[inside])
    assert mask[..., 0].all() and torch.equal(batch["member"][1], torch.ones(500, 3, dtype=torch.long))
    assert set((first % steps).flatten().tolist()) == set(range(steps))
    # member 0's draws do not depend on member 1's generator
    alone = sample_sub_episodes(data[:1], 500, 3, steps, [torch.Generator().manual_seed(1)])
    assert torch.equal(alone["slot"][0], batch["slot"][0])
    with pytest.raises(ValueError, match="whole episodes"):
        sample_sub_episodes(data[:, :19], 4, 3, steps, gens)


def test_the_divergence_reads_the_newest_episodes_of_the_ring_in_the_order_they_were_written():
    cfg, t = training("trust_pcl", "er.buffer_size=2000", "algo.trust_pcl.divergence_episodes=9")
    phases = t.phases
    # 23 episodes written into a ring of ten: episode j in block j mod 10, so the newest nine (14-22) sit
    # in blocks 4-9 and 0-2 (block 3 holds episode 13)
    reward = torch.zeros(2, 2000, 1)
    for block in range(10):
        episode = 20 + block if block < 3 else 10 + block
        reward[:, block * 200:(block + 1) * 200] = episode * 0.25  # exact in float32: totals 50 x episode
    reward[1] *= 10
    data = TensorDict({"next": TensorDict({"reward": reward}, batch_size=[2, 2000])}, batch_size=[2, 2000])
    returns = recent_returns(phases, data, 23)
    assert returns == [[50.0 * e for e in range(14, 23)], [500.0 * e for e in range(14, 23)]]
    early = recent_returns(phases, data[:, :800], 4)  # four episodes so far: blocks 0-3, oldest first
    assert early == [[1000.0, 1050.0, 1100.0, 650.0], [10000.0, 10500.0, 11000.0, 6500.0]]
    with pytest.raises(ValueError, match="expects every episode so far"):
        recent_returns(phases, data[:, :400], 7)


# ------------------------------------------------------------------------- the learner
@pytest.mark.slow
def test_a_trust_pcl_member_equals_its_solo_run_resumes_exactly_and_its_policy_loads(tmp_path):
    run = ["algo=trust_pcl", *FAST, "algo.td.updates_per_step=0.1", "episodes=5", "checkpoint_every=2",
           "algo.trust_pcl.rollout=4"]
    solo = solo_and_resumed_pair(run, tmp_path)
    assert "actor/lambda" in solo.splitlines()[0]
    cfg = load(*run)
    policy = make_policy("trust_pcl", {"actor_hidden": cfg.network.actor_hidden, "activation": cfg.network.activation},
                         6, torch.load(tmp_path / "solo" / "actor.pt"))
    assert policy(np.zeros(6)).shape == (2,)


def test_the_lagged_networks_follow_by_tau_and_both_losses_reach_their_networks():
    cfg, t = training("trust_pcl", "algo.td.tau=0.25")
    lagged, online = t.loss.target_value_network_params, t.loss.value_network_params
    saved = lagged.clone()
    t.phases.updater.step()
    for key in saved.keys(True, True):
        torch.testing.assert_close(lagged[key], saved[key] * 0.75 + online[key].detach() * 0.25)
    lagged_actor = t.loss.target_actor_network_params
    assert not any(p.data_ptr() == q.data_ptr() for p, q in zip(lagged_actor.values(True, True),
                                                              t.loss.actor_network_params.values(True, True)))


@pytest.mark.parametrize("override, message", [
    (["er=prioritised"], "draws whole sub-episodes"),
    (["er.buffer_size=10100"], "multiple of the episode"),
    (["algo.td.n_step=3"], "set algo.td.n_step: 1"),
    (["algo.td.loss_function=l1"], "square of its path consistency"),
    (["algo.trust_pcl.rollout=0"], "algo.trust_pcl.rollout must be"),
    (["algo.trust_pcl.max_divergence=0"], "algo.trust_pcl.max_divergence must be"),
    (["algo.td.critic_blocks=2"], "plain MLP"),
    (["algo.trust_pcl.rollout=1000000000"], "longer than an episode"),
    (["algo.trust_pcl.divergence_episodes=8"], "must be at least 9"),
    (["er.buffer_size=1000"], "holds 5"),
    (["algo.trust_pcl.initial_coefficient=1e12"], "lambda's range"),
    (["er=hybrid"], "use er=memory, not"),
])
def test_bad_trust_pcl_settings_are_refused_with_a_reason(override, message):
    with pytest.raises(ConfigError, match=message):
        load("algo=trust_pcl", *override)


def test_the_options_torch_free_copies_of_the_coefficients_range_are_the_losss():
    from learners.td import trust_pcl as options
    from losses import trust_pcl

    assert options.LAMBDA_MAX == trust_pcl.LAMBDA_RANGE[1] and options.FEWEST_EPISODES == trust_pcl.FEWEST_EPISODES
