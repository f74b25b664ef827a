"""Loss modules against hand-computed values, TorchRL's ClipPPOLoss and known critics."""

import math

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor
from torchrl.objectives import ClipPPOLoss

from learners.solo import CriticNet, GaussianPolicyNet, make_actor, make_critic
from losses import LogClipPPOLoss, SPGLoss
from losses import functional as F

B = 32


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)


def batch(n: int = B) -> TensorDict:
    return TensorDict({
        "observation": torch.rand(n, 6),
        "action": torch.rand(n, 2) * 2 - 1,
        "value_target": torch.randn(n, 1) * 3,
    }, batch_size=[n])


def ppo_loss(**kwargs):
    actor_net = GaussianPolicyNet(6, 2, [16])
    critic = make_critic(CriticNet(6, [16]), state_action=False)
    return LogClipPPOLoss(make_actor(actor_net), critic, **kwargs), actor_net


def spg_loss(critic_net: nn.Module | None = None, **kwargs):
    actor_net = GaussianPolicyNet(6, 2, [16])
    critic = make_critic(critic_net or CriticNet(8, [16]), state_action=True)
    return SPGLoss(make_actor(actor_net), critic, **kwargs), actor_net


# ------------------------------------------------------------------------ pure functions
def test_clipped_surrogate_by_hand():
    ratio = torch.tensor([[0.5], [1.1], [1.5], [0.5], [1.5]])
    adv = torch.tensor([[1.0], [1.0], [1.0], [-1.0], [-1.0]])
    objective, clipped = F.clipped_surrogate(ratio, adv, 0.2, "linear")
    # min(pA, clip(p)A): 0.5 | 1.1 | clip to 1.2 | clip to -0.8 | -1.5
    assert torch.allclose(objective.squeeze(), torch.tensor([0.5, 1.1, 1.2, -0.8, -1.5]))
    assert clipped.squeeze().tolist() == [False, False, True, True, False]


def test_log_space_clip_bounds_and_objective():
    low, high = F.clip_bounds(0.2, "log")
    assert (low, high) == (math.log(0.8), math.log(1.2))
    p = torch.tensor([[-1.0], [0.1], [0.5]])
    adv = torch.tensor([[2.0], [2.0], [-2.0]])
    objective, _ = F.clipped_surrogate(p, adv, 0.2, "log")
    expected = [-2.0, 0.2, -1.0]  # min(pA, clip(p)A) with p in log space
    assert torch.allclose(objective.squeeze(), torch.tensor(expected))
    assert torch.equal(F.ppo_ratio(torch.tensor([1.5]), torch.tensor([1.0]), "log"), torch.tensor([0.5]))


def test_spg_candidates_layout_and_clipping():
    action = torch.tensor([[0.9, -0.9]])
    mean = torch.tensor([[0.0, 0.5]])
    noise = torch.tensor([[[1.0, 1.0], [-3.0, 0.0]]])
    around_mean = F.spg_candidates(action, mean, noise, 0.5, "mean")
    assert torch.allclose(around_mean, torch.tensor([[[0.9, -0.9], [0.0, 0.5], [0.5, 1.0], [-1.0, 0.5]]]))
    around_action = F.spg_candidates(action, mean, noise, 0.5, "action")
    assert torch.allclose(around_action[0, 2:], torch.tensor([[1.0, -0.4], [-0.6, -0.9]]))


def test_best_candidate_takes_first_on_ties():
    candidates = torch.arange(12.0).reshape(2, 3, 2)
    scores = torch.tensor([[1.0, 3.0, 3.0], [5.0, 0.0, 1.0]])
    target, index = F.best_candidate(candidates, scores)
    assert index.tolist() == [1, 0]
    assert target.tolist() == [[2.0, 3.0], [6.0, 7.0]]


# -------------------------------------------------------------------------------- PPO
def test_ppo_matches_torchrl_clip_ppo_in_joint_linear_form():
    """Joint log-probabilities in linear space are exactly TorchRL's ClipPPOLoss."""
    ours, actor_net = ppo_loss(joint_log_prob=True, ratio_space="linear", entropy_coeff=0.02)
    td = batch()
    ours.before_critic_phase(td)
    ours.before_actor_phase(td)
    with torch.no_grad():  # move the policy so that ratios differ from 1 and some are clipped
        for p in actor_net.parameters():
            p.add_(0.3 * torch.randn_like(p))
    theirs_actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
        in_keys=["loc", "scale"], distribution_class=IndependentNormal, return_log_prob=True)
    theirs = ClipPPOLoss(theirs_actor, ours.critic_network, clip_epsilon=0.2, entropy_coeff=0.02,
                         normalize_advantage=False, critic_coeff=1.0, loss_critic_type="l2")
    mine = ours.actor_loss(td.clone())
    td_ref = td.clone()  # TorchRL keeps joint log-probabilities without a trailing dimension
    td_ref["action_log_prob"] = td_ref["action_log_prob"].squeeze(-1)
    ref = theirs(td_ref)
    assert torch.allclose(mine["loss_objective"], ref["loss_objective"], atol=1e-6)
    assert torch.allclose(mine["loss_entropy"], ref["loss_entropy"], atol=1e-6)
    assert 0 < mine["clip_fraction"] < 1
    g_mine = torch.autograd.grad(mine["loss_objective"] + mine["loss_entropy"], list(actor_net.parameters()))
    g_ref = torch.autograd.grad(ref["loss_objective"] + ref["loss_entropy"], list(actor_net.parameters()))
    for a, b in zip(g_mine, g_ref):
        assert torch.allclose(a, b, atol=1e-5)


@pytest.mark.parametrize("space", ["linear", "log"])
def test_ppo_per_dimension_by_hand(space):
    loss, actor_net = ppo_loss(ratio_space=space, entropy_coeff=0.02)
    td = batch()
    td["advantage"] = torch.randn(B, 1)
    td["action_log_prob"] = torch.randn(B, 2) - 1
    loc, scale = actor_net(td["observation"])
    dist = torch.distributions.Normal(loc, scale)
    logp = dist.log_prob(td["action"])
    log_ratio = logp - td["action_log_prob"]
    p = log_ratio.exp() if space == "linear" else log_ratio
    lo, hi = (0.8, 1.2) if space == "linear" else (math.log(0.8), math.log(1.2))
    adv = td["advantage"]
    objective = torch.minimum(p * adv, p.clamp(lo, hi) * adv).mean()
    out = loss.actor_loss(td)
    assert torch.allclose(out["loss_objective"], -objective, atol=1e-6)
    assert torch.allclose(out["loss_entropy"], -0.02 * dist.entropy().mean(), atol=1e-7)


def test_ppo_log_ratio_is_zero_at_the_old_policy():
    loss, _ = ppo_loss(ratio_space="log")
    td = batch()
    loss.before_critic_phase(td)
    loss.before_actor_phase(td)
    out = loss.actor_loss(td)
    assert out["ratio_mean"] == 0 and out["clip_fraction"] == 0 and out["approx_kl"].abs() < 1e-7


def test_ppo_advantage_is_return_minus_value():
    loss, _ = ppo_loss()
    td = batch()
    loss.before_critic_phase(td)
    value = loss.critic_network.module(td["observation"])
    assert torch.allclose(td["advantage"], td["value_target"] - value)
    assert not td["advantage"].requires_grad


def test_critic_loss_is_mean_squared_error():
    loss, _ = ppo_loss()
    td = batch()
    out = loss.critic_loss(td)
    value = loss.critic_network.module(td["observation"])
    assert torch.allclose(out["loss_critic"], ((td["value_target"] - value) ** 2).mean())


# -------------------------------------------------------------------------------- SPG
class PeakedQ(nn.Module):
    """Q(s, a) = -|a - peak|^2: the best candidate is the one nearest ``peak``."""

    def __init__(self, peak):
        super().__init__()
        self.peak = torch.as_tensor(peak)
        self.dummy = nn.Parameter(torch.zeros(()))

    def forward(self, observation, action):
        return -((action - self.peak) ** 2).sum(-1, keepdim=True) + 0 * self.dummy


@pytest.mark.parametrize("prioritised", [False, True])
def test_spg_target_is_the_critics_argmax(prioritised):
    peak = torch.tensor([0.3, -0.6])
    loss, actor_net = spg_loss(PeakedQ(peak), prioritised=prioritised, num_samples=5, temperature=0.7)
    td = batch()
    torch.manual_seed(123)
    out = loss.actor_loss(td)
    torch.manual_seed(123)  # the same perturbations, by hand
    loc, scale = actor_net(td["observation"])
    noise = torch.randn(B, 5, 2)
    candidates = torch.cat([td["action"][:, None], loc.detach()[:, None],
                            (loc.detach()[:, None] + 0.7 * noise).clamp(-1, 1)], dim=1)
    q = -((candidates - peak) ** 2).sum(-1)
    target = candidates[torch.arange(B), q.argmax(1)]
    logp = torch.distributions.Normal(loc, scale).log_prob(target)
    weight = (q.max(1).values - q[:, 1]).unsqueeze(-1) if prioritised else 1.0
    assert torch.allclose(out["loss_objective"], -(weight * logp).mean(), atol=1e-6)
    assert torch.allclose(out["q_target"], q.max(1).values.mean())
    if prioritised:
        assert torch.allclose(out["weight_mean"], weight.mean())
        assert (weight >= 0).all()


def test_spg_stored_action_wins_when_it_is_the_peak():
    td = batch(1)
    loss, _ = spg_loss(PeakedQ(td["action"][0]), num_samples=5)
    out = loss.actor_loss(td)
    assert out["target_is_action"] == 1.0 and out["q_gain"] >= 0


def test_spg_temperature_decays_after_each_actor_phase():
    loss, _ = spg_loss(temperature=1.0, temperature_decay=0.01)
    loss.after_actor_phase()
    loss.after_actor_phase()
    assert loss.temperature.item() == pytest.approx(0.99**2, abs=1e-15)
    assert "temperature" in loss.state_dict()


@pytest.mark.parametrize("make", [spg_loss, ppo_loss])
def test_gradients_reach_only_the_intended_network(make):
    loss, actor_net = make()
    td = batch()
    loss.before_critic_phase(td)
    loss.before_actor_phase(td)
    critic_params = list(loss.qvalue_network.parameters() if isinstance(loss, SPGLoss)
                         else loss.critic_network.parameters())
    actor_out = loss.actor_loss(td)
    (actor_out["loss_objective"] + actor_out["loss_entropy"]).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in actor_net.parameters())
    assert all(p.grad is None for p in critic_params)
    actor_net.zero_grad(set_to_none=True)
    loss.critic_loss(td)["loss_critic"].backward()
    assert all(p.grad is not None for p in critic_params)
    assert all(p.grad is None for p in actor_net.parameters())


def test_forward_returns_actor_and_critic_terms():
    loss, _ = spg_loss()
    out = loss(batch())
    assert {"loss_objective", "loss_entropy", "loss_critic"} <= set(out.keys())
    assert set(SPGLoss.actor_metrics) | set(SPGLoss.critic_metrics) == set(out.keys())


@pytest.mark.parametrize("kwargs, message", [
    ({"sample_around": "best"}, "sample_around must be one of"),
    ({"baseline": "zero"}, "baseline must be one of"),
    ({"num_samples": -1}, "num_samples must be an integer >= 0"),
])
def test_spg_rejects_bad_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        spg_loss(**kwargs)


def test_ppo_rejects_bad_options():
    with pytest.raises(ValueError, match="ratio_space must be one of"):
        ppo_loss(ratio_space="sqrt")
    with pytest.raises(ValueError, match="clip_epsilon must be in"):
        ppo_loss(clip_epsilon=1.5)


def test_fast_module_calls_equal_the_tensordict_path():
    """losses.common calls plain modules directly; wrapped ones take TorchRL's path: same numbers."""
    from tensordict.nn import TensorDictSequential

    loss, actor_net = spg_loss(prioritised=True)
    wrapped_actor = ProbabilisticActor(
        TensorDictSequential(TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"])),
        in_keys=["loc", "scale"], distribution_class=torch.distributions.Normal)
    wrapped_critic = TensorDictSequential(loss.qvalue_network)
    general = SPGLoss(wrapped_actor, wrapped_critic, prioritised=True)
    td = batch()
    for out_fast, out_general in [(loss.critic_loss(td), general.critic_loss(td))]:
        assert torch.equal(out_fast["loss_critic"], out_general["loss_critic"])
    torch.manual_seed(5)
    fast = loss.actor_loss(td)
    torch.manual_seed(5)
    slow = general.actor_loss(td)
    for key in SPGLoss.actor_metrics:
        assert torch.equal(fast[key], slow[key]), key
    assert set(td.keys()) == {"observation", "action", "value_target"}  # inputs left untouched
