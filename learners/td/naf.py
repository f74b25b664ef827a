"""NAF (Normalized Advantage Functions, ``losses.naf.NAFLoss``): one network of V(s), mu(s) and the advantage's
lower-triangular L(s), trained by one loss; it acts with Gaussian noise around mu."""

from __future__ import annotations

from dataclasses import dataclass

from learners.options import ConfigError, at_least
from learners.registry import LearnerSpec
from learners.td import critic_options_given


@dataclass(frozen=True)
class NAFOptions:
    """``algo.naf`` (``losses.naf.NAFLoss``): the acting policy's exploration, mu's pre-tanh penalty."""

    exploration_noise: float  # standard deviation of the Gaussian noise added to mu(s) when acting
    preact_penalty: float = 0.0  # the loss adds this x the mean square of mu's pre-tanh outputs (TD3's)

    def __post_init__(self) -> None:
        at_least("algo.naf.exploration_noise", self.exploration_noise, 0)
        at_least("algo.naf.preact_penalty", self.preact_penalty, 0)


def _check(algo) -> None:
    if critic_options_given(algo):
        raise ConfigError(f"algo {algo.name}: loss naf's value network (V and the advantage's L) is a plain MLP of "
                          "network.critic_hidden; set algo.td.critic_dropout: 0.0, algo.td.critic_layer_norm: false "
                          "and algo.td.critic_blocks: 0")


# its one value network reads the observation: V and the advantage's three entries of L (two actions)
SPEC = LearnerSpec(name="naf", title="NAF", family="td", module=__name__, blocks={"naf": NAFOptions}, check=_check,
                   critic=lambda algo: (1, 4, False), gaussian_actor=False)
METRICS = (("loss_qvalue", "value", "advantage"), ())  # one loss trains mu, V and L


def actor(actor_net):
    """mu(s): the greedy action."""
    from tensordict.nn import TensorDictModule

    return TensorDictModule(actor_net, ["observation"], ["action"])


def critics(cfg, inputs, generators):
    """One network: V(s), then the advantage's lower-triangular L(s)."""
    from tensordict.nn import TensorDictModule

    from learners.networks import StackedCriticNet, reset_parameters
    from losses.naf import lower_entries

    net = cfg.network
    value_net = StackedCriticNet(len(generators), inputs.observation, net.critic_hidden, net.activation,
                                 outputs=1 + lower_entries(inputs.action)).to(generators[0].device)
    reset_parameters(value_net, generators)
    return [value_net], [TensorDictModule(value_net, ["observation"], ["naf"])]


def exploration_noise(cfg) -> float:
    return cfg.algo.naf.exploration_noise


def preact_penalty(cfg) -> float:
    return cfg.algo.naf.preact_penalty


def loss(cfg, networks, generators):
    from losses.naf import NAFLoss

    return NAFLoss(networks.actor, networks.qvalues[0], networks.sampler.action_dim,
                   loss_function=cfg.algo.td.loss_function)


def prepare(runner) -> None:
    from learners.compiling import compile_step

    runner.objective = compile_step(lambda batch: losses(runner, batch), runner.cfg.compile)


def losses(runner, batch):
    """Its loss per member, its V and A means (diagnostics), the minibatch's priorities |y - Q|, and
    ``naf.preact_penalty`` x the mean square of mu's pre-tanh outputs (TD3's remedy for a policy stuck in
    tanh's flat tails; zero by default)."""
    import torch

    from losses.common import PRIORITY_KEY
    from losses.td import member_means

    out = runner.loss(batch)
    values = {key: member_means(out[key]) for key in ("loss_qvalue", "value", "advantage")}
    penalty = torch.zeros_like(values["loss_qvalue"])
    if runner.preact_penalty:
        penalty = runner.preact(runner.actor_net[0], batch)
    return values, batch.get(PRIORITY_KEY), penalty


def step(runner, batch, step, totals):
    """One step of NAF's one loss, which trains mu (the actor's optimiser) and V and L (the critic's)."""
    values, priority, penalty = runner.objective(batch)
    runner.minimise(values["loss_qvalue"] + penalty if runner.preact_penalty else values["loss_qvalue"],
                    runner.optimisers.critic, runner.optimisers.actor)
    runner.updater.step()
    totals.add("critic", values)
    return priority
