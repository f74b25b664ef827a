"""Trust-PCL (``losses.trust_pcl.TrustPCLLoss``): path consistency over sub-episodes of the replay memory
with a relative-entropy trust region against a lagged policy; a Gaussian actor and a value network V(s)."""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, at_least, positive
from learners.registry import LearnerSpec
from learners.td import critic_options_given

LAMBDA_MAX = 1000.0  # losses.trust_pcl.LAMBDA_RANGE's top (kept torch-free here; a test holds them equal)
FEWEST_EPISODES = 9  # losses.trust_pcl.FEWEST_EPISODES


@dataclass(frozen=True)
class TrustPCLOptions:
    """``algo.trust_pcl`` (``losses.trust_pcl.TrustPCLLoss``): the sub-episodes, the trust region and the
    consistency's gradients (``conf/algo/trust_pcl.yaml`` explains each key)."""

    rollout: int  # d: steps per sub-episode (fewer where the episode ends first)
    max_divergence: float  # the trust region: the relative entropy allowed per episode step
    divergence_episodes: int  # the newest this-many episodes of the memory estimate the divergence
    entropy: float  # tau: the entropy coefficient
    clip: float | None  # the consistency is clipped to [-clip, clip] in the gradients (None: not clipped)
    critic_weight: float  # the value loss's weight
    initial_coefficient: float = 0.0  # lambda before its first move

    def __post_init__(self) -> None:
        at_least("algo.trust_pcl.rollout", self.rollout, 1)
        positive("algo.trust_pcl.max_divergence", self.max_divergence)
        at_least("algo.trust_pcl.divergence_episodes", self.divergence_episodes, 1)
        at_least("algo.trust_pcl.entropy", self.entropy, 0)
        if self.clip is not None:
            positive("algo.trust_pcl.clip", self.clip)
        positive("algo.trust_pcl.critic_weight", self.critic_weight)
        at_least("algo.trust_pcl.initial_coefficient", self.initial_coefficient, 0)
        if self.initial_coefficient > LAMBDA_MAX:
            raise ConfigError(f"algo.trust_pcl.initial_coefficient must be in lambda's range [0, {LAMBDA_MAX:g}], "
                              f"got {self.initial_coefficient}")
        if self.divergence_episodes < FEWEST_EPISODES:
            raise ConfigError(f"algo.trust_pcl.divergence_episodes must be at least {FEWEST_EPISODES}: with fewer "
                              f"episodes the trust region is not estimated (lambda stays at {LAMBDA_MAX / 2:g}), got "
                              f"{self.divergence_episodes}")


def _check(algo) -> None:
    td = algo.td or {}
    if critic_options_given(algo):
        raise ConfigError(f"algo {algo.name}: loss trust_pcl's value network is a plain MLP of network.critic_hidden; "
                          "set algo.td.critic_dropout: 0.0, algo.td.critic_layer_norm: false and "
                          "algo.td.critic_blocks: 0")
    if td.get("n_step", 1) != 1:
        raise ConfigError(f"algo {algo.name}: loss trust_pcl draws sub-episodes of algo.trust_pcl.rollout steps from "
                          f"one-step transitions; set algo.td.n_step: 1 (got {td.get('n_step')})")
    if td.get("loss_function", "l2") != "l2":
        raise ConfigError(f"algo {algo.name}: loss trust_pcl minimises the square of its path consistency; set "
                          f"algo.td.loss_function: l2 (got {td.get('loss_function')})")


def _check_run(cfg) -> None:
    algo, er, steps = cfg.algo, cfg.er, cfg.env.episode_steps
    if er.priority is not None:
        raise ConfigError(f"algo {algo.name}: loss trust_pcl draws whole sub-episodes, not prioritised "
                          "transitions; use er=memory")
    if er.buffer_size % steps:
        raise ConfigError(f"algo {algo.name}: loss trust_pcl keeps whole episodes in its memory; "
                          f"er.buffer_size ({er.buffer_size}) must be a multiple of the episode's {steps} steps")
    if er.buffer_size // steps < algo.trust_pcl.divergence_episodes:
        raise ConfigError(f"algo {algo.name}: the trust region is estimated from the newest "
                          f"{algo.trust_pcl.divergence_episodes} episodes of the memory "
                          f"(algo.trust_pcl.divergence_episodes), but er.buffer_size ({er.buffer_size}) holds "
                          f"{er.buffer_size // steps}; give a larger memory or fewer episodes")
    if algo.trust_pcl.rollout > steps:
        raise ConfigError(f"algo {algo.name}: algo.trust_pcl.rollout ({algo.trust_pcl.rollout}) is longer "
                          f"than an episode ({steps} steps); a sub-episode lies inside one")


# its value network reads the observation; an actor and value pair lags behind; a minibatch counts sub-episodes
SPEC = LearnerSpec(name="trust_pcl", title="Trust-PCL", family="td", module=__name__,
                   blocks={"trust_pcl": TrustPCLOptions}, check=_check, check_run=_check_run,
                   critic=lambda algo: (2, 1, False), gaussian_actor=True, prioritised=False,
                   rows=lambda algo, minibatch: minibatch * algo.trust_pcl.rollout)
METRICS = (("loss_value", "consistency"), ("loss_actor", "lambda"))


def actor(actor_net):
    """Its loss scores the memory's actions under pi and the lagged pi~."""
    from tensordict.nn import TensorDictModule

    return TensorDictModule(actor_net, ["observation"], ["loc", "scale"])


def critics(cfg, inputs, generators):
    """V(s)."""
    from tensordict.nn import TensorDictModule

    from learners.networks import StackedCriticNet, reset_parameters

    net = cfg.network
    value_net = StackedCriticNet(len(generators), inputs.observation, net.critic_hidden,
                                 net.activation).to(generators[0].device)
    reset_parameters(value_net, generators)
    return [value_net], [TensorDictModule(value_net, ["observation"], ["state_value"])]


def exploration_noise(cfg) -> None:
    return None  # it samples its policy


def loss(cfg, networks, generators):
    from losses.trust_pcl import TrustPCLLoss

    pcl = cfg.algo.trust_pcl
    return TrustPCLLoss(networks.actor, networks.qvalues[0], gamma=cfg.gamma, rollout=pcl.rollout,
                        entropy=pcl.entropy, max_divergence=pcl.max_divergence, clip=pcl.clip,
                        critic_weight=pcl.critic_weight, members=len(generators), coefficient=pcl.initial_coefficient)


def prepare(runner) -> None:
    from learners.compiling import compile_step

    runner.objective = compile_step(lambda batch: losses(runner, batch), runner.cfg.compile)


def recent_returns(runner, data, episode: int) -> list[list[float]]:
    """Each member's total rewards of the newest ``trust_pcl.divergence_episodes`` episodes of its memory
    ``data`` (``[R, n]``, slot order) before episode ``episode``: episodes 0 .. episode - 1 were written an
    episode at a time into a ring of whole episodes, so episode j sits in block j mod (capacity / steps)."""
    import torch

    steps, (members, n), capacity = runner.steps, data.batch_size, runner.cfg.er.buffer_size
    if n != min(episode * steps, capacity):
        raise ValueError(f"the memory holds {n} transitions before episode {episode}; trust_pcl expects every "
                         f"episode so far, {episode} x {steps} (at most its {capacity})")
    blocks = capacity // steps
    totals = data.get(("next", "reward")).reshape(members, n // steps, steps).double().sum(-1)
    newest = range(max(0, episode - runner.cfg.algo.trust_pcl.divergence_episodes, episode - blocks), episode)
    index = torch.tensor([j % blocks for j in newest], device=totals.device)
    return totals[:, index].tolist()


def losses(runner, batch):
    from losses.td import member_means

    out = runner.loss(batch)
    return {key: member_means(out[key]) for key in ("loss_actor", "loss_value", "consistency")}


def phase(runner, data, minibatch_size: int, totals, episode: int, todo: int) -> None:
    """Its steps before an episode: the trust region's coefficient for each member from its newest episodes
    (``losses.trust_pcl.relative_entropy_coefficient``), then per step: lambda moves 1% towards it, a
    minibatch of sub-episodes, one step of both losses, the lagged networks follow by ``td.tau``."""
    from collectors import sample_sub_episodes

    targets = runner.loss.coefficient_targets(recent_returns(runner, data, episode), runner.steps)
    for _ in range(todo):
        batch = runner.normalised(sample_sub_episodes(data, minibatch_size, runner.cfg.algo.trust_pcl.rollout,
                                                      runner.steps, runner.generators))
        runner.loss.move_coefficient(targets)
        values = runner.objective(batch)
        runner.minimise(values["loss_actor"] + values["loss_value"], runner.optimisers.critic, runner.optimisers.actor)
        runner.updater.step()
        totals.add("critic", {"loss_value": values["loss_value"], "consistency": values["consistency"]})
        totals.add("actor", {"loss_actor": values["loss_actor"], "lambda": runner.loss.coefficient.float()})
