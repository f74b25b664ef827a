"""REDQ: TorchRL's ``REDQLoss`` (``losses.redq.MemberREDQLoss``): an ensemble of Q-networks whose target is
the minimum over a random subset per member, with SAC's learned temperature; its step is its own
loss module's ``population_losses`` (TorchRL's numbers for one member, each member with its own subset)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from learners.options import ConfigError, at_least, capped, positive
from learners.registry import LearnerSpec
from learners.td import critic_options_given, sac
from learners.td.sac import SACOptions


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


def _check(algo) -> None:
    if critic_options_given(algo, ("critic_dropout", "critic_layer_norm")):
        raise ConfigError(f"algo {algo.name}: loss redq's step computes plain or residual Q-networks (algo.td.critic_blocks); "
                          "set algo.td.critic_dropout: 0.0 and algo.td.critic_layer_norm: false")


def _check_run(cfg) -> None:
    if cfg.compile:
        raise ConfigError(f"algo {cfg.algo.name}: compile=true is not supported for redq (each member draws its "
                          "own subset of target networks; its step runs eagerly); use compile=false")


SPEC = LearnerSpec(name="redq", title="REDQ", family="td", module=__name__,
                   blocks={"sac": SACOptions, "redq": REDQOptions}, check=_check, check_run=_check_run,
                   critic=lambda algo: (algo.redq.critics, 1, True), gaussian_actor=True, past_critic=True)
METRICS = sac.METRICS
actor, exploration_noise = sac.actor, sac.exploration_noise


def policy_delay(cfg) -> int:
    return cfg.algo.redq.actor_every(cfg.algo.td.updates_per_step)


def critics(cfg, inputs, generators):
    from learners.td.learner import q_networks

    return q_networks(cfg, inputs, generators, count=cfg.algo.redq.critics)


def loss(cfg, networks, generators):
    from learners.td.learner import entropy_loss_options
    from losses.redq import MemberREDQLoss

    redq = cfg.algo.redq
    options = entropy_loss_options(cfg, networks, generators)
    options["deactivate_vmap"] = True
    return MemberREDQLoss(networks.actor, networks.qvalues, loss_function=cfg.algo.td.loss_function, subset=redq.subset,
                          min_alpha=redq.min_alpha if redq.min_alpha is not None else 0.0,
                          max_alpha=redq.max_alpha if redq.max_alpha is not None else math.inf, **options)


def prepare(runner) -> None:
    from losses.redq import redq_available

    if runner.cfg.compile or runner.actor_net is None or not redq_available(runner.loss, runner.actor_net):
        raise ValueError("loss redq runs eagerly (compile=false) on the learner's own actor network and plain or "
                         "residual Q-networks (MemberREDQLoss.population_losses)")


def step(runner, batch, step, totals):
    """A critic step of the ensemble; every ``policy_delay`` steps the same pass also gives the actor's and
    the temperature's losses (REDQ's one actor step per environment step at ``policy_delay =
    updates_per_step``)."""
    actor_step = (step + 1) % runner.policy_delay == 0
    values, priority = runner.loss.population_losses(runner.actor_net, batch, actor=actor_step)
    if actor_step:
        runner.minimise(sum(values.values()), runner.optimisers.critic, runner.optimisers.actor)
        totals.add("actor", {"loss_actor": values["loss_actor"], "loss_alpha": values["loss_alpha"],
                             "alpha": runner.loss.alpha})
    else:
        runner.minimise(values["loss_qvalue"], runner.optimisers.critic)
    runner.updater.step()
    totals.add("critic", {"loss_qvalue": values["loss_qvalue"]})
    return priority
