"""A TD-MPC2-style planner (Hansen et al., 2024): a latent model (``learners.latent.LatentModel``: encoder,
latent dynamics, reward head, policy prior) and an ensemble of Q-networks on its latent states, trained on
sub-episodes of the replay memory by TD-MPC2's losses (``losses.tdmpc2.TDMPC2Loss``), acting by MPPI in the
latent space at every step (``learners.latent.plan``), the prior's trajectories among the samples and the
previous step's plan as the warm start.

Its steps (``phase``): per gradient step, a minibatch of ``algo.minibatch_size`` sub-episodes of
``algo.tdmpc2.horizon`` steps per member (``collectors.sample_sub_episodes``), the prior's draws from each
member's generator, one step of every loss, the target Q-networks following by ``algo.td.tau``.

Its acting policy (``acting_policy``): ``PlanningSampler``, or with ``algo.tdmpc2.planning: false`` the prior's
draws as SAC acts (the same learner without planning: what planning adds is measured against it). The saved
actor (``actor.pt``) is the whole model; a planning run's deterministic policy (``evaluate.py``, the
leaderboard, ``eval_seeds``) plans with it and the Q-networks (``critic.pt``) without the executed action's
noise (``evaluation_policy``).
"""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, at_least, capped, positive
from learners.registry import LearnerSpec
from learners.td import critic_options_given


@dataclass(frozen=True)
class TDMPC2Options:
    """``algo.tdmpc2`` (``conf/algo/tdmpc2.yaml`` explains each key)."""

    latent: int = capped((65_536, "units"))
    group: int = capped((65_536, "units"))  # the latent state's units are groups of this many, each a softmax (SimNorm)
    width: int = capped((65_536, "units"))
    critics: int = capped((1_000, "Q-networks"))
    bins: int = capped((10_000, "support points"))
    v_max: float  # the support is [-v_max, v_max] in symlog units
    horizon: int = capped((1_000, "steps"))
    rho: float
    consistency_weight: float
    reward_weight: float
    value_weight: float
    entropy: float
    scale_tau: float
    samples: int = capped((100_000, "trajectories"))
    policy_samples: int = capped((100_000, "trajectories"))
    elites: int = capped((100_000, "trajectories"))
    iterations: int = capped((1_000, "iterations"))
    temperature: float
    min_std: float
    max_std: float
    planning: bool = True  # act by MPPI (False: by sampling the prior, as SAC samples its actor)

    def __post_init__(self) -> None:
        for key in ("latent", "width", "critics", "horizon", "samples", "elites", "iterations"):
            at_least(f"algo.tdmpc2.{key}", getattr(self, key), 1)
        at_least("algo.tdmpc2.group", self.group, 2, " (a softmax over one unit is always 1: the state would carry nothing)")
        at_least("algo.tdmpc2.bins", self.bins, 2)
        at_least("algo.tdmpc2.policy_samples", self.policy_samples, 0)
        for key in ("v_max", "temperature", "min_std", "scale_tau"):
            positive(f"algo.tdmpc2.{key}", getattr(self, key))
        for key in ("consistency_weight", "reward_weight", "value_weight", "entropy"):
            at_least(f"algo.tdmpc2.{key}", getattr(self, key), 0)
        if self.latent % self.group:
            raise ConfigError(f"algo.tdmpc2.latent ({self.latent}) must be a multiple of algo.tdmpc2.group "
                              f"({self.group}): the latent state is made of groups of that many units")
        if not 0 < self.rho <= 1:
            raise ConfigError(f"algo.tdmpc2.rho must be in (0, 1], got {self.rho}")
        if self.scale_tau > 1:
            raise ConfigError(f"algo.tdmpc2.scale_tau must be in (0, 1], got {self.scale_tau}")
        if self.max_std < self.min_std:
            raise ConfigError(f"algo.tdmpc2.max_std ({self.max_std}) is below algo.tdmpc2.min_std ({self.min_std})")
        if self.policy_samples >= self.samples:
            raise ConfigError(f"algo.tdmpc2.policy_samples ({self.policy_samples}) must be below algo.tdmpc2.samples "
                              f"({self.samples}): the rest are the Gaussian's samples")
        if self.elites > self.samples:
            raise ConfigError(f"algo.tdmpc2.elites ({self.elites}) must be at most algo.tdmpc2.samples ({self.samples})")


def _check(algo) -> None:
    td = algo.td or {}
    if critic_options_given(algo):
        raise ConfigError(f"algo {algo.name}: loss tdmpc2's networks are its own (algo.tdmpc2: latent, width); set "
                          "algo.td.critic_dropout: 0.0, algo.td.critic_layer_norm: false and algo.td.critic_blocks: 0")
    if td.get("n_step", 1) != 1:
        raise ConfigError(f"algo {algo.name}: loss tdmpc2 rolls its model over sub-episodes of one-step transitions; "
                          f"set algo.td.n_step: 1 (got {td.get('n_step')})")
    if td.get("loss_function", "l2") != "l2":
        raise ConfigError(f"algo {algo.name}: loss tdmpc2's value and reward losses are cross-entropies; keep "
                          f"algo.td.loss_function: l2 (got {td.get('loss_function')})")


def _check_run(cfg) -> None:
    algo, er, steps = cfg.algo, cfg.er, cfg.env.episode_steps
    if er.priority is not None:
        raise ConfigError(f"algo {algo.name}: loss tdmpc2 draws whole sub-episodes, not prioritised transitions; "
                          "use er=memory")
    if er.buffer_size % steps:
        raise ConfigError(f"algo {algo.name}: loss tdmpc2 keeps whole episodes in its memory; er.buffer_size "
                          f"({er.buffer_size}) must be a multiple of the episode's {steps} steps")
    if algo.tdmpc2.horizon > steps:
        raise ConfigError(f"algo {algo.name}: algo.tdmpc2.horizon ({algo.tdmpc2.horizon}) is longer than an "
                          f"episode ({steps} steps)")
    if cfg.compile:
        raise ConfigError(f"algo {algo.name}: loss tdmpc2 runs eagerly; set compile: false")


def _sizes(algo, obs: int, action: int) -> tuple[int, int, int]:
    """(parameters per member, widest layer, layers) of its model and Q-networks (the memory estimate)."""
    o = algo.tdmpc2
    latent, width = o.latent, o.width

    def mlp(*sizes: int) -> int:
        return sum((a + 3) * b for a, b in zip(sizes, sizes[1:]))  # weights, biases, layer norms

    model = (mlp(obs, width, latent) + mlp(latent + action, width, latent) + mlp(latent + action, width, o.bins)
             + mlp(latent, width, 2 * action))
    return model + o.critics * mlp(latent + action, width, width, o.bins), max(width, latent, o.bins), 3


def _acting(algo, steps: int) -> int:
    """Floats the planner holds per member: an episode's draws, and each planning iteration's samples through the
    widest layer (forward values and temporaries)."""
    o = algo.tdmpc2
    if not o.planning:
        return 0
    h, p, n, i = o.horizon, o.policy_samples, o.samples, o.iterations
    per_step = h * p * 2 + i * (n - p) * h * 2 + i * n * 2 + 2 + 1
    return steps * per_step + n * (max(o.width, o.latent, o.bins) * 8 + h * 2 * 4)


SPEC = LearnerSpec(name="tdmpc2", title="TD-MPC2-style planner", family="td", module=__name__,
                   blocks={"tdmpc2": TDMPC2Options}, check=_check, check_run=_check_run,
                   critic=lambda algo: (algo.tdmpc2.critics, algo.tdmpc2.bins, True), gaussian_actor=True,
                   prioritised=False, rows=lambda algo, minibatch: minibatch * 2 * algo.tdmpc2.horizon,
                   networks=_sizes, acting=_acting)
METRICS = (("loss_value", "loss_consistency", "loss_reward"), ("loss_actor", "q_scale"))


def _options(algo) -> TDMPC2Options:
    """``algo.tdmpc2`` from a run's configuration or from its settings (a mapping: ``summary.json``)."""
    block = algo["tdmpc2"] if isinstance(algo, dict) else algo.tdmpc2
    return TDMPC2Options(**block) if isinstance(block, dict) else block


def _support(options: TDMPC2Options):
    from losses.tdmpc2 import Support

    return Support(options.v_max, options.bins)


def actor_network(members, obs_dim, action_dim, network, algo):
    """The latent model: what acts (through the planner), is saved and evaluated (its prior)."""
    from learners.latent import LatentModel
    from learners.td.learner import _setting

    options = _options(algo)
    return LatentModel(members, obs_dim, action_dim, options.latent, options.width, options.bins, options.group,
                       _setting(network, "activation"))


def actor(actor_net):
    return actor_net  # the loss trains the model itself


def critics(cfg, inputs, generators):
    """The Q-networks Q(z, a) -> the support's logits, two hidden layers of ``width`` units, layer-normalised."""
    from learners.networks import reset_parameters
    from learners.td.learner import q_modules

    options, members = cfg.algo.tdmpc2, len(generators)
    nets = []
    for _ in range(options.critics):
        q = _q_network(members, options, options.latent + inputs.action, cfg.network.activation).to(generators[0].device)
        reset_parameters(q, generators)
        nets.append(q)
    return nets, q_modules(nets, inputs)


def _q_network(members: int, options: TDMPC2Options, inputs: int, activation: str):
    """One Q-network (z, a) -> the support's logits for ``members`` stacked networks: two layer-normalised hidden
    layers of ``width`` units."""
    from learners.networks import StackedCriticNet

    return StackedCriticNet(members, inputs, [options.width, options.width], activation, outputs=options.bins,
                            layer_norm=True)


def _plan_options(options: TDMPC2Options, gamma: float):
    from learners.latent import PlanOptions

    o = options
    return PlanOptions(horizon=o.horizon, samples=o.samples, policy_samples=o.policy_samples, elites=o.elites,
                       iterations=o.iterations, temperature=o.temperature, min_std=o.min_std, max_std=o.max_std,
                       gamma=float(gamma))


def exploration_noise(cfg) -> None:
    return None


def loss(cfg, networks, generators):
    from losses.tdmpc2 import TDMPC2Loss

    o = cfg.algo.tdmpc2
    return TDMPC2Loss(networks.actor_net, networks.qvalues, support=_support(o), horizon=o.horizon, rho=o.rho,
                      consistency_weight=o.consistency_weight, reward_weight=o.reward_weight,
                      value_weight=o.value_weight, entropy=o.entropy, scale_tau=o.scale_tau,
                      members=len(generators), generators=generators)


def acting_policy(cfg, networks, loss):
    """MPPI with the model and the loss's Q-networks as they stand (``PlanningSampler``), from the off-policy
    sampler ``networks.sampler`` (its warm-up, observation statistics and generators); without
    ``algo.tdmpc2.planning``, that sampler itself (the prior's draws, as SAC acts)."""
    from learners.latent import PlanningSampler

    o = cfg.algo.tdmpc2
    if not o.planning:
        return networks.sampler
    return PlanningSampler.wrap(networks.sampler, loss.planning_value, _plan_options(o, cfg.gamma), _support(o))


def evaluation_policy(net, critic: dict | None, network, algo, gamma: float | None):
    """The network a run's deterministic policy calls (``engine.evaluation.make_policy``): when it planned, MPPI
    with its saved model ``net`` and Q-networks ``critic`` (``critic.pt``'s weights) without the executed
    action's noise (``learners.latent.PlanningActor``), discounting by the run's ``gamma``; else ``net`` (the
    prior's tanh(loc))."""
    from learners.latent import PlanningActor
    from learners.td.learner import _setting

    o = _options(algo)
    if not o.planning:
        return net
    if critic is None or gamma is None:
        raise ValueError("a planning run's policy plans with its Q-networks (critic.pt) and the run's gamma")
    first = critic["module.net.layers.0.weight"]  # [Q-networks, width, inputs]: the saved ensemble's layout
    qvalues = _q_network(first.shape[0], o, first.shape[-1], _setting(network, "activation"))
    qvalues.load_state_dict({key.removeprefix("module."): value for key, value in critic.items()})
    return PlanningActor(net, qvalues.eval(), _plan_options(o, gamma), _support(o))


def prepare(runner) -> None:
    runner.objective = lambda batch: losses(runner, batch)


def losses(runner, batch):
    out = runner.loss(batch)
    return {key: out[key] for key in ("loss_consistency", "loss_reward", "loss_value", "loss_actor", "q_scale")}


def phase(runner, data, minibatch_size: int, totals, episode: int, todo: int) -> None:
    """Per step: a minibatch of sub-episodes per member, the prior's draws, one step of every loss (the model and
    Q-networks by the critic's optimiser and the actor's, the prior by the actor's), the target Q-networks
    follow by ``td.tau``."""
    from collectors import sample_sub_episodes

    horizon = runner.cfg.algo.tdmpc2.horizon
    for _ in range(todo):
        batch = runner.normalised(sample_sub_episodes(data, minibatch_size, horizon, runner.steps, runner.generators))
        runner.loss.draw(batch)
        values = runner.objective(batch)
        model = values["loss_consistency"] + values["loss_reward"] + values["loss_value"]
        runner.minimise(model + values["loss_actor"], runner.optimisers.critic, runner.optimisers.actor)
        runner.updater.step()
        totals.add("critic", {key: values[key] for key in ("loss_value", "loss_consistency", "loss_reward")})
        totals.add("actor", {"loss_actor": values["loss_actor"], "q_scale": values["q_scale"]})
