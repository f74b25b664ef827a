"""TD3: TorchRL's ``TD3Loss`` (``losses.td3.MemberTD3Loss``): a deterministic tanh actor with Gaussian exploration
noise, twin Q-networks, target policy smoothing and an actor step every ``policy_delay`` critic steps."""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import at_least
from learners.registry import LearnerSpec


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


SPEC = LearnerSpec(name="td3", title="TD3", family="td", module=__name__, blocks={"td3": TD3Options},
                   critic=lambda algo: (2, 1, True), gaussian_actor=False)
METRICS = (("loss_qvalue",), ("loss_actor",))


def actor(actor_net):
    """The target actor adds the smoothing noise the loss draws per member."""
    from tensordict.nn import TensorDictModule

    from losses.td3 import SMOOTHING_KEY, SmoothedActor

    return TensorDictModule(SmoothedActor(actor_net), ["observation", SMOOTHING_KEY], ["action"])


def critics(cfg, inputs, generators):
    from learners.td.learner import q_networks

    return q_networks(cfg, inputs, generators, count=2)


def exploration_noise(cfg) -> float:
    return cfg.algo.td3.exploration_noise


def policy_delay(cfg) -> int:
    return cfg.algo.td3.policy_delay


def preact_penalty(cfg) -> float:
    return cfg.algo.td3.preact_penalty


def loss(cfg, networks, generators):
    from learners.td.learner import action_spec
    from losses.td3 import MemberTD3Loss

    td3 = cfg.algo.td3
    return MemberTD3Loss(networks.actor, networks.qvalues, action_spec(networks, generators),
                         policy_noise=td3.policy_noise, noise_clip=td3.noise_clip,
                         loss_function=cfg.algo.td.loss_function, generators=generators,
                         deactivate_vmap=not cfg.compile)


def fused_available(loss, actor_net) -> bool:
    from losses.td3 import fused_td3_available

    return fused_td3_available(loss, actor_net)


def prepare(runner) -> None:
    from learners.compiling import compile_step

    runner.critic_objective = compile_step(lambda batch: critic_losses(runner, batch), runner.cfg.compile)
    runner.actor_objective = compile_step(lambda batch: actor_losses(runner, batch), runner.cfg.compile)


def critic_losses(runner, batch):
    """The Q loss per member and the minibatch's priorities (the largest error of the Q-networks; TorchRL's
    TD3 reports squared errors per Q-network)."""
    from losses.td import member_means
    from losses.td3 import fused_td3_critic_losses

    if runner.fused:
        return fused_td3_critic_losses(runner.loss, runner.actor_net, batch)
    loss_qvalue, meta = runner.loss.value_loss(batch)
    return member_means(loss_qvalue), meta["td_error"].max(0).values.sqrt()


def actor_losses(runner, batch):
    """TorchRL's actor loss -Q(s, mu(s)) per member, plus ``td3.preact_penalty`` x the mean square of the
    actor's pre-tanh outputs u(s) (mu = tanh(u)): a gradient that pulls u back from tanh's flat tails,
    where -Q's vanishes (TD3's collapse at full brake, docs/beyond.md)."""
    from losses.td import member_means
    from losses.td3 import fused_td3_actor_losses

    if runner.fused:
        value = fused_td3_actor_losses(runner.loss, runner.actor_net, batch)
    else:
        value = member_means(runner.loss.actor_loss(batch)[0])
    if runner.preact_penalty:  # its own pass through the actor, as before the fused step (the same bits)
        value = value + runner.preact(runner.loss.actor_network.module.net[0], batch)
    return value


def step(runner, batch, step, totals):
    loss_qvalue, priority = runner.critic_objective(batch)
    runner.minimise(loss_qvalue, runner.optimisers.critic)
    totals.add("critic", {"loss_qvalue": loss_qvalue})
    if (step + 1) % runner.policy_delay == 0:
        loss_actor = runner.actor_objective(batch)
        runner.minimise(loss_actor, runner.optimisers.actor)
        runner.updater.step()
        totals.add("actor", {"loss_actor": loss_actor})
    return priority
