"""SimbaV2-style SAC (Lee et al., 2025): SAC whose actor and Q-networks are hyperspherical
(``learners.hyperspherical``: weights and features on the unit sphere, weights projected back after every
step), whose critics are categorical (``losses.simbav2.DistributionalSACLoss``), with observations normalised
by running statistics (``algo.td.observation_norm``) and rewards scaled so that returns fit the critic's support.

The reward scale (``before_steps``): before each block of gradient steps, from the episodes in each member's
replay memory, the discounted return from each episode's start G_t = r_t + gamma * G_(t-1); the scale is
``max(std(G), max|G| / v_max)`` (SimbaV2's, over the memory's episodes rather than a running estimate over
every episode), so that returns fit ``[-v_max, v_max]``. It is a function of the memory, so a resumed run
computes the same scale.
"""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, at_least, capped, positive
from learners.registry import LearnerSpec
from learners.td import critic_options_given, sac
from learners.td.sac import SACOptions


@dataclass(frozen=True)
class SimbaV2Options:
    """``algo.simbav2`` (``conf/algo/simbav2.yaml`` explains each key)."""

    critics: int = capped((1_000, "Q-networks"))  # 1: SimbaV2's for tasks without terminal states; 2: clipped double Q
    bins: int = capped((10_000, "support points"))  # of each Q-network's categorical distribution
    v_max: float  # the support is [-v_max, v_max], in scaled returns
    actor_width: int = capped((65_536, "units"))
    actor_blocks: int = capped((64, "blocks"))
    critic_width: int = capped((65_536, "units"))
    critic_blocks: int = capped((64, "blocks"))

    def __post_init__(self) -> None:
        at_least("algo.simbav2.critics", self.critics, 1)
        at_least("algo.simbav2.bins", self.bins, 2)
        positive("algo.simbav2.v_max", self.v_max)
        for key in ("actor_width", "critic_width"):
            at_least(f"algo.simbav2.{key}", getattr(self, key), 1)
        for key in ("actor_blocks", "critic_blocks"):
            at_least(f"algo.simbav2.{key}", getattr(self, key), 0)


def _check(algo) -> None:
    if critic_options_given(algo):
        raise ConfigError(f"algo {algo.name}: loss simbav2's Q-networks are hyperspherical (algo.simbav2); set "
                          "algo.td.critic_dropout: 0.0, algo.td.critic_layer_norm: false and algo.td.critic_blocks: 0")


def _check_run(cfg) -> None:
    steps, capacity = cfg.env.episode_steps, cfg.er.buffer_size
    if capacity % steps:
        raise ConfigError(f"algo {cfg.algo.name}: the reward scale reads whole episodes from the replay memory; "
                          f"er.buffer_size ({capacity}) must be a multiple of the episode's {steps} steps")


def _sizes(algo, obs: int, action: int) -> tuple[int, int, int]:
    """(parameters per member, widest layer, layers) of its hyperspherical networks (the memory estimate):
    an embedder, LERP blocks four times wider inside, a head; the Q-networks' target copies count in the estimate's
    per-parameter copies."""
    o = algo.simbav2

    def net(inputs: int, width: int, blocks: int, outputs: int) -> int:
        return (inputs + 1) * width + blocks * 8 * width * width + width * outputs + 4 * width

    parameters = net(obs, o.actor_width, o.actor_blocks, 2 * action) + o.critics * net(
        obs + action, o.critic_width, o.critic_blocks, o.bins)
    return parameters, max(4 * o.actor_width, 4 * o.critic_width, o.bins), 2 + max(o.actor_blocks, o.critic_blocks) * 2


SPEC = LearnerSpec(name="simbav2", title="SimbaV2-style SAC", family="td", module=__name__,
                   blocks={"sac": SACOptions, "simbav2": SimbaV2Options}, check=_check, check_run=_check_run,
                   critic=lambda algo: (algo.simbav2.critics, algo.simbav2.bins, True), gaussian_actor=True,
                   networks=_sizes)
METRICS = (("loss_qvalue", "reward_scale"), sac.METRICS[1])
actor, exploration_noise = sac.actor, sac.exploration_noise


def _options(algo) -> SimbaV2Options:
    """``algo.simbav2`` from a run's configuration or from its settings (a mapping: ``summary.json``)."""
    block = algo["simbav2"] if isinstance(algo, dict) else algo.simbav2
    return SimbaV2Options(**block) if isinstance(block, dict) else block


def actor_network(members, obs_dim, action_dim, network, algo):
    from learners.hyperspherical import HyperActorNet

    options = _options(algo)
    return HyperActorNet(members, obs_dim, action_dim, options.actor_width, options.actor_blocks)


def critics(cfg, inputs, generators):
    from learners.hyperspherical import HyperCriticNet
    from learners.networks import reset_parameters
    from learners.td.learner import q_modules

    options, members = cfg.algo.simbav2, len(generators)
    nets = []
    for _ in range(options.critics):
        q = HyperCriticNet(members, inputs.observation + inputs.extras + inputs.action, options.bins,
                           options.critic_width, options.critic_blocks).to(generators[0].device)
        reset_parameters(q, generators)
        nets.append(q)
    return nets, q_modules(nets, inputs)


def loss(cfg, networks, generators):
    from learners.td.learner import entropy_loss_options
    from losses.simbav2 import DistributionalSACLoss

    options = cfg.algo.simbav2
    return DistributionalSACLoss(networks.actor, networks.qvalues, support=(-options.v_max, options.v_max, options.bins),
                                 **entropy_loss_options(cfg, networks, generators))


def prepare(runner) -> None:
    from learners.compiling import compile_step
    from learners.hyperspherical import hyper_weights

    runner.objective = compile_step(lambda batch: losses(runner, batch), runner.cfg.compile)
    runner.hyper_weights = (hyper_weights(runner.actor_net)
                            + hyper_weights(runner.qvalue_nets[0], runner.loss.qvalue_network_params))


def before_steps(runner, data) -> None:
    """Each member's reward scale from the episodes of its memory (``data``, ``[R, n]``; the module's docstring)."""
    import torch

    reward = data.get(("next", "reward")).double()  # [R, n, 1], whole episodes in slot order
    members, steps = reward.shape[0], runner.steps
    episodes = reward.reshape(members, -1, steps)
    gamma = float(runner.loss.value_estimator.gamma)
    returns, total = torch.zeros_like(episodes), torch.zeros_like(episodes[..., 0])
    for t in range(steps):
        total = gamma * total + episodes[..., t]
        returns[..., t] = total
    flat = returns.reshape(members, -1)
    scale = torch.maximum((flat.var(1, correction=0) + 1e-8).sqrt(), flat.abs().amax(1) / runner.cfg.algo.simbav2.v_max)
    runner.loss.reward_scale.copy_(scale.to(runner.loss.reward_scale.dtype))


def losses(runner, batch):
    from losses.common import PRIORITY_KEY
    from losses.td import member_means

    out = runner.loss(batch)
    values = {key: member_means(out[key]) for key in ("loss_qvalue", "loss_actor", "loss_alpha")}
    return values, batch.get(PRIORITY_KEY)


def step(runner, batch, step, totals):
    """One step of the three losses together, every hyper-linear weight back onto the sphere, then the target
    networks' soft update."""
    from learners.hyperspherical import project

    values, priority = runner.objective(batch)
    runner.minimise(sum(values.values()), runner.optimisers.critic, runner.optimisers.actor)
    project(runner.hyper_weights)
    runner.updater.step()
    totals.add("critic", {"loss_qvalue": values["loss_qvalue"], "reward_scale": runner.loss.reward_scale})
    totals.add("actor", {"loss_actor": values["loss_actor"], "loss_alpha": values["loss_alpha"],
                         "alpha": runner.loss.alpha})
    return priority
