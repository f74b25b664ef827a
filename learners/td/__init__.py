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
from typing import Protocol

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
    start_from: str | None = None  # a finished run's folder (or a population's, or a search's weights) whose actor
    #                                starts this run's (engine.start; docs/beyond.md's decisive experiment)
    start_critics_from: str | None = None  # a finished run's folder (or a population's) whose critic.pt starts the
    #                                Q-networks and their targets
    critic_first_episodes: int = capped((10_000_000, "episodes"), default=0)  # the steps before episodes 1..this
    #                                train the critics only (TDPhaseRunner.actor_held)

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
        at_least("algo.td.critic_first_episodes", self.critic_first_episodes, 0)
        for key in ("start_from", "start_critics_from"):
            value = getattr(self, key)
            if value is not None and (not isinstance(value, str) or not value.strip()):
                raise ConfigError(f"algo.td.{key} must be null or a path, got {value!r}")
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


class LearnerModule(Protocol):
    """What an off-policy learner's module provides (``learners/td/<name>.py``; the registry checks the
    required members when it finds the module, ``learners.registry.check_module``). Its functions import
    torch inside themselves: the module's top level stays torch-free. One of ``step`` or ``phase``
    (``ONE_OF``); the hooks a learner may add are ``OPTIONAL``'s."""

    SPEC: object  # its learners.registry.LearnerSpec
    METRICS: tuple  # (critic names, actor names): its diagnostics, metrics.csv's columns

    def actor(self, actor_net):
        """The TensorDict actor its loss takes (``learner.tanh_normal_actor`` for a learned temperature)."""

    def critics(self, cfg, inputs, generators):
        """Its critic networks and their TensorDict modules, member r's initial weights from ``generators[r]``."""

    def exploration_noise(self, cfg):
        """The acting policy's Gaussian noise for a deterministic actor, else None."""

    def loss(self, cfg, networks, generators):
        """Its loss module."""

    def prepare(self, runner):
        """Its compiled objectives (``learners.compiling.compile_step``) and any check of what was built."""


ONE_OF = {
    "step": "(runner, batch, step, totals) -> priority: one gradient step on a minibatch",
    "phase": "(runner, data, minibatch_size, totals, episode, todo): the steps of a learner that draws its own "
             "minibatches (Trust-PCL's sub-episodes)",
}
OPTIONAL = {
    "policy_delay": "(cfg) -> int: critic steps per actor step",
    "preact_penalty": "(cfg) -> float: the actor's pre-tanh penalty (TD3's, NAF's)",
    "fused_available": "(loss, actor_net) -> bool: whether its fused step computes this loss's settings (the fused "
                       "step runs only while learners.fast_paths finds the code it copies as recorded)",
    "actor_network": "(members, obs_dim, action_dim, network, algo): an actor other than network.actor_hidden's MLP",
    "before_steps": "(runner, data): what it sets from the replay memory before a block of steps",
    "acting_policy": "(cfg, networks, loss): an acting policy that reads the trained loss (a planner)",
    "evaluation_policy": "(net, critic, network, algo, gamma): a deterministic policy that is more than its actor",
}

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


def build(cfg, env, generators, memory, starts=None):
    """The members' networks, loss, optimisers and update phase: a ``learners.base.Learner``; ``starts``
    (``engine.start``): the members' actors' starting weights."""
    from learners.td.learner import build

    return build(cfg, env, generators, memory, starts)
