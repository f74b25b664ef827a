"""The off-policy learners: bootstrapped targets, gradient steps paid per environment step, target (or
lagged) networks, a replay memory. TorchRL's losses, and NAF's and Trust-PCL's (``losses.naf.NAFLoss``,
``losses.trust_pcl.TrustPCLLoss``), which TorchRL does not ship. Each learner is a module here
(``sac``, ``tqc``, ``crossq``, ``redq``, ``td3``, ``naf``, ``trust_pcl``; ``learners.registry``); the
machinery they share (networks, acting policy, the steps' schedule) is ``learners.td.learner``.

The family's torch-free half: the option blocks its learners read (validated before torch loads), its
rules, and ``build``, which imports the torch half on first use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from learners.options import ACTIVATIONS, ConfigError, at_least, capped, choice, positive
from racing.history import MAX_HISTORY

DESCRIPTION = "the off-policy learners"
OFF_POLICY = True  # trains on a replay memory only: er=memory or er=prioritised
KEYS = ()  # its schedule is in the td: block
LOSS_FUNCTIONS = ("l2", "l1", "smooth_l1")


PESSIMISM_LIMIT = 10.0  # algo.td.pessimism: standard deviations of the Q-networks


@dataclass(frozen=True)
class TDOptions:
    """The off-policy schedule every learner of the family reads (``algo.td``; ``conf/algo/sac.yaml`` explains each key)."""

    updates_per_step: float = capped((1_000, "gradient steps per environment step"))
    warmup_episodes: int
    tau: float | None  # None: no target networks (crossq)
    loss_function: str
    n_step: int = capped((10_000, "steps"), default=1)  # TD targets over n environment steps (collectors.returns.n_step_transitions)
    critic_dropout: float = 0.0  # DroQ: dropout of the Q-networks' hidden units (each member's own masks)
    critic_layer_norm: bool = False  # DroQ: layer normalisation of the Q-networks' hidden units
    critic_blocks: int = capped((64, "residual blocks"), default=0)  # BRO: residual blocks of a layer-normalised Q-network (0: the MLP of network.critic_hidden)
    critic_width: int | None = capped((65_536, "units"), default=None)  # BRO: its hidden units (None: network.critic_hidden[0])
    critic_activation: str | None = None  # BRO: its activation (None: network.activation)
    critic_weight_decay: float = 0.0  # decoupled weight decay of the Q-networks (AdamW's)
    reset_every: int = 0  # re-initialise every network, temperature and optimiser every this-many episodes
    #                       (0: never); the replay memory is kept
    observation_norm: bool = False  # actor and critics see running-normalised observations (learners.networks.ObservationNorm)
    privileged_critic: bool = False  # the Q-networks also see the car's true state (RacingSim.true_state); training only
    critic_history: int = 0  # the Q-networks also see the car's last this-many observations and actions (its own past)
    pessimism: float | None = None  # the target and the actor combine the Q-networks as mean - this x std
    #                                 (losses.td.q_reduce); None: their minimum (TorchRL's)

    def __post_init__(self) -> None:
        positive("algo.td.updates_per_step", self.updates_per_step)
        at_least("algo.td.warmup_episodes", self.warmup_episodes, 0)
        if self.tau is not None and not 0 < self.tau <= 1:
            raise ConfigError(f"algo.td.tau must be in (0, 1], got {self.tau}")
        choice("algo.td.loss_function", self.loss_function, LOSS_FUNCTIONS)
        at_least("algo.td.n_step", self.n_step, 1)
        if not 0 <= self.critic_dropout < 1:
            raise ConfigError(f"algo.td.critic_dropout must be in [0, 1), got {self.critic_dropout}")
        at_least("algo.td.critic_blocks", self.critic_blocks, 0)
        if self.critic_width is not None:
            at_least("algo.td.critic_width", self.critic_width, 1)
        if self.critic_activation is not None:
            choice("algo.td.critic_activation", self.critic_activation, ACTIVATIONS)
        at_least("algo.td.critic_weight_decay", self.critic_weight_decay, 0)
        at_least("algo.td.reset_every", self.reset_every, 0)
        at_least("algo.td.critic_history", self.critic_history, 0)
        if self.critic_history > MAX_HISTORY:
            raise ConfigError(f"algo.td.critic_history must be at most {MAX_HISTORY} past steps, got {self.critic_history}")
        if self.pessimism is not None and not -PESSIMISM_LIMIT <= self.pessimism <= PESSIMISM_LIMIT:
            raise ConfigError(f"algo.td.pessimism must be within [-{PESSIMISM_LIMIT:g}, {PESSIMISM_LIMIT:g}] standard "
                              f"deviations of the Q-networks (or null: their minimum), got {self.pessimism}")
        if self.critic_blocks and (self.critic_dropout or self.critic_layer_norm):
            raise ConfigError("algo.td.critic_blocks > 0 makes a residual Q-network, layer-normalised throughout "
                              "and without dropout; set algo.td.critic_dropout: 0.0 and algo.td.critic_layer_norm: "
                              f"false (got {self.critic_dropout} and {self.critic_layer_norm})")
        if not self.critic_blocks and (self.critic_width is not None or self.critic_activation is not None):
            from learners.registry import LEARNERS

            own = ", ".join(f"algo.{name}" for name, spec in LEARNERS.items() if spec.networks is not None)
            raise ConfigError("algo.td.critic_width and algo.td.critic_activation shape BRO's residual Q-network; "
                              "they need algo.td.critic_blocks >= 1 (the MLP takes network.critic_hidden and "
                              "network.activation; a learner with its own networks sizes them in its own block: "
                              f"{own})")

    def updates_before(self, episode: int, steps: int) -> int:
        """Gradient steps taken in all, up to the start of episode ``episode`` (``episode`` episodes of
        ``steps`` transitions collected): none while only warm-up episodes are collected, then
        ``updates_per_step`` for every step collected since the last warm-up episode began
        (fractions carry over)."""
        first = max(self.warmup_episodes, 1)  # the first episode preceded by gradient steps
        return math.floor(max(0, episode - first + 1) * steps * self.updates_per_step + 1e-9)


def linear_schedule(start: float, end: float, episode: int, first: int, last: int) -> float:
    """``start`` until episode ``first``, then linearly to ``end`` at episode ``last`` and after (float64:
    the same value on every CPU)."""
    fraction = min(1.0, max(0.0, (episode - first) / max(1, last - first)))
    return start + (end - start) * fraction


@dataclass(frozen=True)
class SACOptions:
    """``algo.sac``: TorchRL's ``SACLoss``'s temperature, and that of the losses built like it
    (``TQCLoss``, ``CrossQLoss``)."""

    alpha_init: float
    target_entropy: float | None  # None: TorchRL's "auto", minus the action dimension
    fixed_alpha: bool
    target_entropy_end: float | None = None  # None: the target stays; else it moves linearly from target_entropy
    #                                          at the first gradient step to this at the last episode

    def __post_init__(self) -> None:
        positive("algo.sac.alpha_init", self.alpha_init)
        for key in ("target_entropy", "target_entropy_end"):
            value = getattr(self, key)
            if value is not None and not -1e6 <= value <= 1e6:
                raise ConfigError(f"algo.sac.{key} must be within [-1e6, 1e6] nats (or null), got {value}")
        if self.target_entropy_end is not None and self.fixed_alpha:
            raise ConfigError("algo.sac.target_entropy_end moves the target the learned temperature follows; with "
                              "algo.sac.fixed_alpha: true there is none (set one of them back)")


@dataclass(frozen=True)
class TD3Options:
    """``algo.td3`` (TorchRL's ``TD3Loss``)."""

    exploration_noise: float
    policy_noise: float
    noise_clip: float
    policy_delay: int
    preact_penalty: float = 0.0  # the actor loss adds this x the mean square of its pre-tanh outputs

    def __post_init__(self) -> None:
        for key in ("exploration_noise", "policy_noise", "noise_clip", "preact_penalty"):
            at_least(f"algo.td3.{key}", getattr(self, key), 0)
        at_least("algo.td3.policy_delay", self.policy_delay, 1)


@dataclass(frozen=True)
class TQCOptions:
    """``algo.tqc`` (TorchRL's ``TQCLoss``): the ensemble of quantile critics and the truncation."""

    critics: int = capped((1_000, "Q-networks"))  # each outputting `quantiles` quantiles of the return
    quantiles: int = capped((10_000, "quantiles per Q-network"))
    drop_per_critic: int  # the target drops the highest critics * drop_per_critic of the pooled quantiles

    def __post_init__(self) -> None:
        at_least("algo.tqc.critics", self.critics, 1)
        at_least("algo.tqc.quantiles", self.quantiles, 1)
        at_least("algo.tqc.drop_per_critic", self.drop_per_critic, 0)
        if self.drop_per_critic >= self.quantiles:
            raise ConfigError(f"algo.tqc.drop_per_critic must be below algo.tqc.quantiles ({self.quantiles}), "
                              f"got {self.drop_per_critic}: the target would keep no quantile")


@dataclass(frozen=True)
class CrossQOptions:
    """``algo.crossq`` (TorchRL's ``CrossQLoss``, batch-normalised critics)."""

    policy_delay: int  # one actor (and temperature) step every this-many critic steps
    batch_norm_momentum: float  # running statistics <- (1 - m) * running + m * batch (evaluation mode)

    def __post_init__(self) -> None:
        at_least("algo.crossq.policy_delay", self.policy_delay, 1)
        if not 0 < self.batch_norm_momentum <= 1:
            raise ConfigError(f"algo.crossq.batch_norm_momentum must be in (0, 1], got {self.batch_norm_momentum}")


@dataclass(frozen=True)
class REDQOptions:
    """``algo.redq`` (TorchRL's ``REDQLoss``): the ensemble, the target's random subset, the actor's
    schedule and the temperature's bounds."""

    critics: int = capped((1_000, "Q-networks"))  # in the ensemble
    subset: int  # target networks whose minimum makes each member's target, drawn anew per minibatch
    policy_delay: int | None  # one actor (and temperature) step every this-many critic steps (None: one per
    #                           environment step, updates_per_step rounded; ``actor_every``)
    min_alpha: float | None = None  # TorchRL's bounds on the temperature (None: unbounded)
    max_alpha: float | None = None

    def __post_init__(self) -> None:
        at_least("algo.redq.critics", self.critics, 2)
        at_least("algo.redq.subset", self.subset, 1)
        if self.subset >= self.critics:
            raise ConfigError(f"algo.redq.subset must be below algo.redq.critics ({self.critics}), got {self.subset}: "
                              "the target takes the minimum over a random subset of the ensemble")
        if self.policy_delay is not None:
            at_least("algo.redq.policy_delay", self.policy_delay, 1)
        for key in ("min_alpha", "max_alpha"):
            if getattr(self, key) is not None:
                positive(f"algo.redq.{key}", getattr(self, key))
        if self.min_alpha is not None and self.max_alpha is not None and self.min_alpha > self.max_alpha:
            raise ConfigError(f"algo.redq.min_alpha ({self.min_alpha}) is above algo.redq.max_alpha ({self.max_alpha})")

    def actor_every(self, updates_per_step: float) -> int:
        """Critic steps per actor step: ``policy_delay``, or one actor step per environment step."""
        return self.policy_delay if self.policy_delay is not None else max(1, round(updates_per_step))


@dataclass(frozen=True)
class NAFOptions:
    """``algo.naf`` (``losses.naf.NAFLoss``): the acting policy's exploration, mu's pre-tanh penalty."""

    exploration_noise: float  # standard deviation of the Gaussian noise added to mu(s) when acting
    preact_penalty: float = 0.0  # the loss adds this x the mean square of mu's pre-tanh outputs (TD3's)

    def __post_init__(self) -> None:
        at_least("algo.naf.exploration_noise", self.exploration_noise, 0)
        at_least("algo.naf.preact_penalty", self.preact_penalty, 0)


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


BLOCKS = {"td": TDOptions}  # the family's own block (each learner declares its others: learners.registry)
CRITIC_OPTIONS = ("critic_dropout", "critic_layer_norm", "critic_blocks")  # DroQ's and BRO's Q-networks


def critic_options_given(algo, keys: tuple[str, ...] = CRITIC_OPTIONS) -> bool:
    """Whether ``algo.td`` (as given) sets any of the critic options ``keys``: the learners whose critic is
    not a plain MLP of Q-values (CrossQ's, NAF's, Trust-PCL's; REDQ's step) refuse them in their check."""
    td = algo.td or {}
    return any(td.get(key) for key in keys)


def check(algo, learner) -> None:
    """The family's rules, for ``learner`` (its ``learners.registry`` spec): target networks follow
    ``algo.td.tau`` where the learner keeps them (CrossQ keeps none: its own check); the critic's view
    of the car's true state and past only where the learner's step feeds it; weight decay below 1/lr."""
    td = algo.td or {}
    if learner.target_networks and td.get("tau", 0.005) is None:
        raise ConfigError(f"algo {algo.name}: loss {algo.loss} updates target networks by algo.td.tau; "
                          "give a value in (0, 1]")
    if td.get("pessimism") is not None and not learner.pessimism:
        from learners.registry import LEARNERS

        able = [name for name, spec in LEARNERS.items() if spec.pessimism]
        raise ConfigError(f"algo {algo.name}: algo.td.pessimism is built for the losses {', '.join(able)} (the way "
                          f"their target and actor combine the Q-networks); loss {algo.loss} keeps its own: set it to null")
    for key, given in (("privileged_critic", td.get("privileged_critic") is True),
                       ("critic_history", isinstance(td.get("critic_history"), int) and td.get("critic_history") > 0)):
        if not given:
            continue
        if not learner.past_critic:
            from learners.registry import LEARNERS

            able = [name for name, spec in LEARNERS.items() if spec.past_critic]
            raise ConfigError(f"algo {algo.name}: algo.td.{key} is built for the losses {', '.join(able)} "
                              f"(their steps feed what the Q-networks see besides (s, a)); loss {algo.loss} has none")
        if td.get("n_step", 1) != 1:
            raise ConfigError(f"algo {algo.name}: algo.td.{key} takes one-step transitions; set algo.td.n_step: 1 "
                              f"(got {td.get('n_step')})")
    decay = td.get("critic_weight_decay") or 0.0
    if isinstance(decay, (int, float)) and isinstance(algo.critic_lr, (int, float)) and decay * algo.critic_lr >= 1:
        raise ConfigError(f"algo {algo.name}: algo.td.critic_weight_decay x critic_lr must be below 1 (each step scales "
                          f"the Q-networks by 1 - lr x decay), got {decay} x {algo.critic_lr}")


def build(cfg, env, generators, memory):
    """The members' networks, loss, optimisers and update phase: a ``learners.base.Learner``."""
    from learners.td.learner import build

    return build(cfg, env, generators, memory)
