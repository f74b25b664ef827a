"""CrossQ: TorchRL's ``CrossQLoss`` (``losses.crossq.MemberCrossQLoss``): batch-normalised Q-networks that score
(s, a) and (s', a') in one pass, no target networks, an actor step every ``policy_delay`` critic steps."""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, at_least
from learners.registry import LearnerSpec
from learners.td import critic_options_given, sac
from learners.td.sac import SACOptions


@dataclass(frozen=True)
class CrossQOptions:
    """``algo.crossq`` (TorchRL's ``CrossQLoss``, batch-normalised critics)."""

    policy_delay: int  # one actor (and temperature) step every this-many critic steps
    batch_norm_momentum: float  # running statistics <- (1 - m) * running + m * batch (evaluation mode)

    def __post_init__(self) -> None:
        at_least("algo.crossq.policy_delay", self.policy_delay, 1)
        if not 0 < self.batch_norm_momentum <= 1:
            raise ConfigError(f"algo.crossq.batch_norm_momentum must be in (0, 1], got {self.batch_norm_momentum}")


def _check(algo) -> None:
    td = algo.td or {}
    if td.get("tau", 0.005) is not None:
        raise ConfigError(f"algo {algo.name}: loss crossq has no target networks; set algo.td.tau: null "
                          f"(got {td.get('tau', 0.005)})")
    if critic_options_given(algo):
        raise ConfigError(f"algo {algo.name}: loss crossq's Q-networks are batch-normalised; set "
                          "algo.td.critic_dropout: 0.0, algo.td.critic_layer_norm: false and algo.td.critic_blocks: 0")


def _check_run(cfg) -> None:
    if cfg.er.priority is not None:
        raise ConfigError(f"algo {cfg.algo.name}: TorchRL's CrossQLoss does not weight by priority; use er=memory")
    if cfg.compile:
        raise ConfigError(f"algo {cfg.algo.name}: compile=true is not supported for crossq (its batch "
                          "normalisation updates running statistics in place); use compile=false")


SPEC = LearnerSpec(name="crossq", title="CrossQ", family="td", module=__name__,
                   blocks={"sac": SACOptions, "crossq": CrossQOptions}, check=_check, check_run=_check_run,
                   critic=lambda algo: (2, 1, True), gaussian_actor=True, target_networks=False, prioritised=False)
METRICS = sac.METRICS
actor, exploration_noise = sac.actor, sac.exploration_noise


def policy_delay(cfg) -> int:
    return cfg.algo.crossq.policy_delay


def critics(cfg, inputs, generators):
    """Twin batch-normalised Q-networks of (s, a)."""
    from learners.networks import StackedBNCriticNet, reset_parameters
    from learners.td.learner import q_modules

    net, members, device = cfg.network, len(generators), generators[0].device
    nets = []
    for _ in range(2):
        q = StackedBNCriticNet(members, inputs.observation + inputs.action, net.critic_hidden, net.activation,
                               momentum=cfg.algo.crossq.batch_norm_momentum).to(device)
        reset_parameters(q, generators)
        nets.append(q)
    return nets, q_modules(nets, inputs)


def loss(cfg, networks, generators):
    from learners.td.learner import entropy_loss_options
    from losses.crossq import MemberCrossQLoss

    options = entropy_loss_options(cfg, networks, generators)
    options["deactivate_vmap"] = True  # its batch norm updates running statistics in place
    return MemberCrossQLoss(networks.actor, networks.qvalues, loss_function=cfg.algo.td.loss_function, **options)


def fused_available(loss, actor_net) -> bool:
    from losses.crossq import fused_crossq_available

    return fused_crossq_available(loss, actor_net)


def prepare(runner) -> None:
    return None  # eager only (checked with the configuration)


def step(runner, batch, step, totals):
    """A critic step (current and next state in one batch-normalised pass), then, every ``policy_delay``
    steps, an actor and temperature step against the updated critics."""
    from losses.crossq import fused_crossq_actor_losses, fused_crossq_critic_losses
    from losses.td import member_means

    loss = runner.loss
    if runner.fused:
        loss_qvalue, priority = fused_crossq_critic_losses(loss, runner.actor_net, batch)
    else:
        loss_qvalue, meta = loss.qvalue_loss(batch)
        loss_qvalue, priority = member_means(loss_qvalue), meta["td_error"]
    runner.minimise(loss_qvalue, runner.optimisers.critic)
    totals.add("critic", {"loss_qvalue": loss_qvalue})
    if (step + 1) % runner.policy_delay == 0:
        if runner.fused:
            loss_actor, loss_alpha = fused_crossq_actor_losses(loss, runner.actor_net, batch)
        else:
            loss_actor, actor_meta = loss.actor_loss(batch)
            loss_actor = member_means(loss_actor)
            loss_alpha = member_means(loss.alpha_loss(actor_meta["log_prob"]))
        runner.minimise(loss_actor + loss_alpha, runner.optimisers.actor)
        totals.add("actor", {"loss_actor": loss_actor, "loss_alpha": loss_alpha, "alpha": loss.alpha})
    return priority
