"""algo=simbav2: hyperspherical networks (learners.hyperspherical), the categorical critic's projection and
loss (losses.simbav2), the reward scale (learners.td.simbav2), each against hand-computed values; train.py
trains and evaluates (a member equals its solo run and a run resumes exactly: tests/test_offpolicy.py)."""

import json
import math

import numpy as np
import pytest
import torch

from engine.config import ConfigError
from learners.base import MetricTotals
from learners.hyperspherical import (EPS, HyperEmbedder, HyperLERPBlock, StackedHyperLinear, hyper_weights,
                                     l2normalise, project)
from losses.simbav2 import categorical_projection
from losses.td import ACTION_NOISE_KEY
from tests.test_config import load
from tests.test_offpolicy import A, B, training, transitions
from tests.test_train import read_rows, run_train


# ------------------------------------------------------------------ hyperspherical normalisation
def test_l2normalise_puts_rows_on_the_unit_sphere_and_leaves_zero_at_zero():
    x = torch.tensor([[3.0, 4.0], [0.0, 0.0], [1e-12, 0.0]])
    assert torch.equal(l2normalise(x)[0], torch.tensor([0.6, 0.8]))
    assert torch.equal(l2normalise(x)[1], torch.zeros(2))
    assert torch.allclose(l2normalise(x)[2], torch.tensor([1e-12 / EPS, 0.0]))  # below EPS: divided by EPS


def test_hyper_linear_rows_are_unit_vectors_at_the_start_and_after_projection():
    layer = StackedHyperLinear(2, 5, 3)
    layer.reset_parameters([torch.Generator().manual_seed(1), torch.Generator().manual_seed(2)])
    assert torch.allclose(layer.weight.norm(dim=-1), torch.ones(2, 3))
    rows = layer.weight[0] @ layer.weight[0].T  # orthogonal rows
    assert torch.allclose(rows, torch.eye(3), atol=1e-6)
    with torch.no_grad():
        layer.weight.mul_(torch.tensor([2.0, 0.5]).view(2, 1, 1))
    project(hyper_weights(layer))
    assert torch.allclose(layer.weight.norm(dim=-1), torch.ones(2, 3))


def test_the_embedder_and_a_lerp_block_compute_simbav2_s_formulas():
    """Embedder: normalise([x, 3]), a hyper-linear map, the scaler, normalise; block: normalise(h + alpha *
    (normalise(W2 relu(s * W1 h) + eps) - h)), each by hand for one member."""
    g = [torch.Generator().manual_seed(0)]
    embed, block = HyperEmbedder(1, 4, 8, 3.0), HyperLERPBlock(1, 8, blocks=1)
    for layer in (*embed.modules(), *block.modules()):
        if hasattr(layer, "stacked_init"):
            layer.reset_parameters(g)
    with torch.no_grad():  # scalers away from their start, to test their formula
        embed.scaler.weight.mul_(1.7)
        block.alpha.weight.mul_(0.3)
        block.scaler.weight.mul_(2.0)
    x = torch.tensor([[[0.5, -1.0, 2.0, 0.0]]])
    shifted = torch.cat([x, torch.full((1, 1, 1), 3.0)], -1)
    u = shifted / shifted.norm(dim=-1, keepdim=True)
    s_embed = embed.scaler.weight[0] * (math.sqrt(2 / 8) / math.sqrt(2 / 8))
    h = u @ embed.linear.weight[0].T * s_embed
    h = h / h.norm(dim=-1, keepdim=True)
    assert torch.allclose(embed(x), h, atol=1e-6)
    scale = math.sqrt(2 / 8) / 2
    inner = torch.relu(h @ block.up.weight[0].T * block.scaler.weight[0] * (scale / scale)) + EPS
    update = inner @ block.down.weight[0].T
    update = update / update.norm(dim=-1, keepdim=True)
    alpha = block.alpha.weight[0] * ((1 / 2) / (1 / math.sqrt(8)))
    out = h + alpha * (update - h)
    assert torch.allclose(block(h), out / out.norm(dim=-1, keepdim=True), atol=1e-6)


# ------------------------------------------------------------------ the categorical critic
def test_the_projection_splits_each_atom_between_its_two_neighbours():
    probs = torch.tensor([0.2, 0.5, 0.3])
    atoms = torch.tensor([-1.5, 0.25, 0.5])  # clipped to -1; 3/4 and 1/4; half and half
    assert torch.allclose(categorical_projection(probs, atoms, -1.0, 1.0), torch.tensor([0.2, 0.525, 0.275]))
    on_points = torch.tensor([0.0, 1.0, 7.0])  # an atom on a point keeps its mass there
    assert torch.allclose(categorical_projection(probs, on_points, -1.0, 1.0), torch.tensor([0.0, 0.2, 0.8]))
    many = torch.rand(4, 6, 11, generator=torch.Generator().manual_seed(0))
    probs = many.softmax(-1)
    projected = categorical_projection(probs, many * 30 - 15, -5.0, 5.0)
    assert torch.allclose(projected.sum(-1), torch.ones(4, 6)) and (projected >= 0).all()


@pytest.mark.parametrize("critics", [1, 2])
def test_the_critic_loss_is_the_cross_entropy_to_the_projected_target(critics):
    """By hand from the networks and the drawn noise: the target network's distribution at (s', a') (with two
    Q-networks, the one whose expected value is lower), its support moved to r / scale + gamma * (z - alpha *
    log pi(a'|s')) and projected; the loss the cross-entropy summed over the Q-networks; the actor's loss
    alpha * log pi(a|s) - min over the Q-networks of the expected value at (s, a)."""
    cfg, t = training("simbav2", f"algo.simbav2.critics={critics}", "algo.simbav2.bins=11", seeds=(A, B))
    loss = t.loss
    loss.reward_scale.copy_(torch.tensor([2.0, 0.5]))
    data = transitions(2, 16)
    data["next", "terminated"][1, :3] = True
    loss.draw(data)
    out = loss(data.clone())
    actor_net, critic = t.networks.actor_net, loss.qvalue_network.module
    support = torch.linspace(-5, 5, 11)

    def sample(observation, noise):
        loc, scale = actor_net(observation)
        pre = loc + noise * scale
        action = torch.tanh(pre)
        return action, (torch.distributions.Normal(loc, scale).log_prob(pre) - torch.log1p(-action.pow(2))).sum(-1)

    def logits(params, observation, action):
        out = []
        for q in range(params.shape[0]):
            with params[q].to_module(loss.qvalue_network):
                out.append(critic(observation, action))
        return torch.stack(out)

    alpha = loss.log_alpha.exp().detach().view(2, 1)
    with torch.no_grad():
        nxt = data["next"]
        next_action, next_log_prob = sample(nxt["observation"], nxt[ACTION_NOISE_KEY])
        probs = logits(loss.target_qvalue_network_params, nxt["observation"], next_action).softmax(-1)
        chosen = probs[(probs * support).sum(-1).argmin(0), torch.arange(2)[:, None], torch.arange(16)]
        going = (~nxt["terminated"]).float()
        atoms = (nxt["reward"] / torch.tensor([2.0, 0.5]).view(2, 1, 1)
                 + cfg.gamma * going * (support - (alpha * next_log_prob).unsqueeze(-1)))
        target = categorical_projection(chosen, atoms, -5.0, 5.0)
        predicted = logits(loss.qvalue_network_params, data["observation"], data["action"]).log_softmax(-1)
        action, log_prob = sample(data["observation"], data[ACTION_NOISE_KEY])
        values = (logits(loss.qvalue_network_params, data["observation"], action).softmax(-1) * support).sum(-1)
    assert torch.allclose(out["loss_qvalue"], -(target * predicted).sum(-1).sum(0), atol=1e-5)
    assert torch.allclose(out["loss_actor"], alpha * log_prob - values.min(0)[0], atol=1e-5)


def test_the_reward_scale_is_that_of_the_memory_s_discounted_returns():
    from learners.td.simbav2 import before_steps

    cfg, t = training("simbav2", "env.options.max_steps=4", "er.buffer_size=8", "algo.minibatch_size=4", seeds=(A, B))
    rewards = torch.tensor([[1.0, 2.0, 0.0, -10.0, 1.0, 1.0, 1.0, 1.0], [0.5] * 8])
    data = transitions(2, 8)
    data["next", "reward"] = rewards.unsqueeze(-1)
    before_steps(t.phases, data)
    gamma = cfg.gamma
    for member in range(2):
        returns = []
        for episode in range(2):
            g = 0.0
            for r in rewards[member, 4 * episode: 4 * episode + 4].tolist():
                g = gamma * g + r
                returns.append(g)
        std = float(np.std(returns))
        expected = max(math.sqrt(std ** 2 + 1e-8), max(abs(v) for v in returns) / 5.0)
        assert float(t.loss.reward_scale[member]) == pytest.approx(expected, rel=1e-6)


def test_every_step_puts_the_weights_back_on_the_sphere():
    cfg, t = training("simbav2", seeds=(A,))
    batch = transitions(1, 32)
    t.loss.draw(batch)
    t.phases.steps_of.step(t.phases, batch, 0, MetricTotals())
    assert len(t.phases.hyper_weights) == 12  # the actor's 7, the Q-network's 5
    for weight in t.phases.hyper_weights:
        assert torch.allclose(weight.norm(dim=-1), torch.ones(weight.shape[:-1]), atol=1e-6)
    assert all(p.is_leaf for p in t.optimisers.critic.params)  # one Q-network: parameters of its own


@pytest.mark.parametrize("override, message", [
    (["algo.td.critic_blocks=2"], "loss simbav2's Q-networks are hyperspherical"),
    (["algo.td.critic_width=32"], "in its own block: algo.simbav2"),
    (["algo.td.pessimism=0"], "algo.td.pessimism is built for the losses"),
    (["er.buffer_size=1100"], "must be a multiple of the episode's 200 steps"),
    (["algo.simbav2.bins=1"], "algo.simbav2.bins must be"),
])
def test_bad_settings_are_refused_with_a_reason(override, message):
    with pytest.raises(ConfigError, match=message):
        load("algo=simbav2", *override)


# ------------------------------------------------------------------ whole runs (member == solo run, exact
# resume: tests/test_offpolicy.py's, parametrised with simbav2)
@pytest.mark.slow
def test_train_py_trains_and_evaluates(tmp_path):
    result = run_train("algo=simbav2", "seed=3", "episodes=2", "algo.td.warmup_episodes=1",
                       "algo.td.updates_per_step=0.05", "progress=false", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["algo"] == "simbav2" and summary["status"] == "completed"
    assert summary["paths"][0]["critic"] == "loss module"
    rows = read_rows(tmp_path / "metrics.csv")
    assert float(rows[1]["critic/loss_qvalue"]) > 0 and float(rows[1]["critic/reward_scale"]) > 0


def test_the_memory_estimate_sees_simbav2_s_own_widths():
    from engine.config import RunConfig
    from engine.limits import check_ram

    with pytest.raises(ConfigError, match="this run needs about "):
        check_ram(RunConfig.compose("algo=simbav2", "er=memory", "algo.simbav2.critic_width=65536"),
                  available=16 * 2**30)
