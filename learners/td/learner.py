"""The off-policy learners in a population (TorchRL's SAC, TQC, CrossQ, REDQ and TD3 losses, NAF's and
Trust-PCL's): the torch half of ``learners.td``.

The same run as the paper's algorithms (``engine.runner``: env, collector, replay memory,
run folders, checkpoints, divergence, populations); what differs is built here:

- networks: stacked members (``learners.networks``) of the sizes in ``network.*``; SAC's actor
  outputs a tanh-squashed Gaussian (``TanhNormal``), TD3's and NAF's a deterministic tanh action; two
  Q-networks Q(s, a) (NAF: one network of V(s) and the advantage's L(s)), each member's initial
  weights drawn from its own generator;
- the acting policy (``OffPolicySampler``): uniform random actions for ``td.warmup_episodes``
  episodes, then SAC samples its policy and TD3 and NAF add Gaussian noise, each member's noise
  from its own generator;
- the updates (``TDPhaseRunner``): before each episode, the gradient steps owed to the
  environment steps collected since the last ones (``td.updates_per_step``), each on a
  minibatch per member from its memory (uniform or prioritised) and the loss's noise drawn from
  the member's generator (``draw``), with TorchRL's soft target updates (``SoftUpdate``, its step
  in one foreach call: ``MemberSoftUpdate``); TD3 steps its actor (and targets) every
  ``policy_delay`` critic steps.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import SoftUpdate

from collectors import ReplayMemory, sample_minibatch, sample_sub_episodes
from learners.base import Learner, MetricTotals, Optimisers, diverged_members, freeze_member, prioritised_minibatch
from learners.compiling import compile_step
from learners.networks import (BlockSampler, NormalisedActor, ObservationNorm, StackedBNCriticNet, StackedCriticNet,
                               StackedMLP, StackedResidualCriticNet, reset_parameters)
from learners.optim import MemberAdam
from learners.td import ENTROPY_LOSSES, GAUSSIAN_ACTORS, linear_schedule
from losses.naf import NAFLoss, lower_entries
from losses.trust_pcl import TrustPCLLoss
from losses.td import (ACTION_NOISE_KEY, CRITIC_EXTRAS, PRIORITY_KEY, SMOOTHING_KEY, DrawnTanhNormal, MemberCrossQLoss,
                       MemberREDQLoss, MemberSACLoss, MemberTD3Loss, MemberTQCLoss, SmoothedActor,
                       fused_crossq_actor_losses, fused_crossq_available, fused_crossq_critic_losses,
                       fused_sac_available, fused_sac_losses, fused_td3_actor_losses, fused_td3_available,
                       fused_td3_critic_losses, fused_tqc_available, fused_tqc_losses, member_means, redq_available,
                       redq_losses)

FUSED = True  # the eager steps of SAC (DroQ, BRO), TQC, CrossQ and TD3 on plain tensors (losses.td.fused_*: the
#               same bits as TorchRL's loss modules, faster); False: through the loss modules (speed.floor
#               --module, speed/recipe_cost.py's *-module recipes)

TD_TRANSITION_KEYS = ("observation", "action", ("next", "observation"), ("next", "reward"), ("next", "done"),
                      ("next", "terminated"))


def critic_extras(td) -> list[str]:
    """What the Q-networks read besides (s, a), in ``losses.td.CRITIC_EXTRAS``' order: the env's ``privileged``
    (``td.privileged_critic``: the car's true state) and ``history`` (``td.critic_history``: its past steps)."""
    wanted = {"privileged": td.privileged_critic, "history": td.critic_history}
    return [key for key in CRITIC_EXTRAS if wanted[key]]


@dataclass
class Networks:
    actor_net: nn.Module  # stacked: observation -> SAC (loc, scale) / TD3 and NAF action
    qvalue_nets: list[nn.Module]  # the Q-networks as built (their trained copies live in the loss; NAF: its one
    #                               value network, observation -> [V, L's entries], trained as built)
    actor: nn.Module  # the TensorDict actor TorchRL's loss takes
    qvalues: list[TensorDictModule]
    sampler: "OffPolicySampler"
    norm: ObservationNorm | None = None  # algo.td.observation_norm: the members' running observation statistics

    @property
    def policy_net(self) -> nn.Module:
        """The actor as it acts and is saved: behind the observations' normalisation when there is one."""
        return NormalisedActor(self.norm, self.actor_net) if self.norm is not None else self.actor_net

    @property
    def critic_net(self) -> nn.Module:
        return nn.ModuleList(self.qvalue_nets)


class _Tanh(nn.Module):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(x)


def make_actor_net(loss: str, members: int, obs_dim: int, action_dim: int, hidden: Sequence[int],
                   activation: str) -> nn.Module:
    """The members' stacked actor: SAC's (TQC's, CrossQ's, REDQ's) and Trust-PCL's ``[R, ..., obs] -> (loc, scale)``
    of a Gaussian (squashed by tanh when sampled), TD3's and NAF's ``[R, ..., obs] -> tanh action``."""
    if loss in GAUSSIAN_ACTORS:
        body = StackedMLP(members, [obs_dim, *hidden, 2 * action_dim], activation, linear_output=True)
        return nn.Sequential(body, NormalParamExtractor(scale_mapping="biased_softplus_1.0", scale_lb=1e-4))
    body = StackedMLP(members, [obs_dim, *hidden, action_dim], activation, linear_output=True)
    return nn.Sequential(body, _Tanh())


def unbuilt(loss: str, where: str) -> NotImplementedError:
    """The error of a loss listed in ``learners.td.LOSSES`` that a part of this module does not build yet:
    each part names every loss it serves, so a new one fails here instead of running as another."""
    return NotImplementedError(f"learners.td.learner.{where} has no branch for loss {loss!r}; add one "
                               "(docs/learners.md lists every place a new loss needs)")


def make_networks(cfg, env, generators: Sequence[torch.Generator]) -> Networks:
    """Actor, then the Q-networks, each member's weights from its generator (Glorot, zero biases)."""
    algo, net, members = cfg.algo, cfg.network, len(generators)
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    device = generators[0].device
    actor_net = make_actor_net(algo.loss, members, obs_dim, action_dim, net.actor_hidden, net.activation).to(device)
    if algo.loss in ENTROPY_LOSSES:  # its reparameterised draws use the noise the loss draws per member
        actor = ProbabilisticActor(TensorDictModule(actor_net, ["observation"], ["loc", "scale"]),
                                   in_keys={"loc": "loc", "scale": "scale", "noise": ACTION_NOISE_KEY},
                                   distribution_class=DrawnTanhNormal,
                                   distribution_kwargs={"low": -1.0, "high": 1.0}, return_log_prob=False)
    elif algo.loss == "naf":  # mu(s): the greedy action
        actor = TensorDictModule(actor_net, ["observation"], ["action"])
    elif algo.loss == "trust_pcl":  # its loss scores the memory's actions under pi and the lagged pi~
        actor = TensorDictModule(actor_net, ["observation"], ["loc", "scale"])
    elif algo.loss == "td3":  # the target actor adds the smoothing noise the loss draws per member
        actor = TensorDictModule(SmoothedActor(actor_net), ["observation", SMOOTHING_KEY], ["action"])
    else:
        raise unbuilt(algo.loss, "make_networks")
    reset_parameters(actor_net, generators)
    norm = ObservationNorm(members, obs_dim).to(device) if algo.td.observation_norm else None
    qvalue_nets = []
    if algo.loss == "naf":  # one network: V(s), then the advantage's lower-triangular L(s)
        value_net = StackedCriticNet(members, obs_dim, net.critic_hidden, net.activation,
                                     outputs=1 + lower_entries(action_dim)).to(device)
        reset_parameters(value_net, generators)
        sampler = OffPolicySampler(actor_net, generators, action_dim, block=cfg.env.episode_steps,
                                   warmup_blocks=algo.td.warmup_episodes, noise=algo.naf.exploration_noise, norm=norm)
        return Networks(actor_net, [value_net], actor, [TensorDictModule(value_net, ["observation"], ["naf"])], sampler,
                        norm)
    if algo.loss == "trust_pcl":  # V(s)
        value_net = StackedCriticNet(members, obs_dim, net.critic_hidden, net.activation).to(device)
        reset_parameters(value_net, generators)
        sampler = OffPolicySampler(actor_net, generators, action_dim, block=cfg.env.episode_steps,
                                   warmup_blocks=algo.td.warmup_episodes, norm=norm)
        return Networks(actor_net, [value_net], actor, [TensorDictModule(value_net, ["observation"], ["state_value"])],
                        sampler, norm)
    extras = critic_extras(algo.td)
    extra_width = sum(env.observation_spec[key].shape[-1] for key in extras)
    if algo.loss == "tqc":
        critics, outputs = algo.tqc.critics, algo.tqc.quantiles
    else:  # twin Q-networks (sac, crossq, td3) or REDQ's ensemble
        critics, outputs = (algo.redq.critics if algo.loss == "redq" else 2), 1
    for _ in range(critics):
        if algo.loss == "crossq":  # batch-normalised
            q = StackedBNCriticNet(members, obs_dim + action_dim, net.critic_hidden, net.activation,
                                   momentum=algo.crossq.batch_norm_momentum).to(device)
        elif algo.td.critic_blocks:  # BRO's residual, layer-normalised Q-network
            q = StackedResidualCriticNet(members, obs_dim + extra_width + action_dim,
                                         algo.td.critic_width or net.critic_hidden[0], algo.td.critic_blocks,
                                         algo.td.critic_activation or net.activation, outputs=outputs).to(device)
        else:
            q = StackedCriticNet(members, obs_dim + extra_width + action_dim, net.critic_hidden, net.activation,
                                 outputs=outputs, dropout=algo.td.critic_dropout, layer_norm=algo.td.critic_layer_norm,
                                 generators=generators).to(device)
        reset_parameters(q, generators)
        qvalue_nets.append(q)
    inputs = ["observation", *extras, "action"]  # concatenated in this order
    qvalues = [TensorDictModule(q, inputs, ["state_action_value"]) for q in qvalue_nets]
    noise = algo.td3.exploration_noise if algo.loss == "td3" else None
    sampler = OffPolicySampler(actor_net, generators, action_dim, block=cfg.env.episode_steps,
                               warmup_blocks=algo.td.warmup_episodes, noise=noise, norm=norm)
    return Networks(actor_net, qvalue_nets, actor, qvalues, sampler, norm)


class OffPolicySampler(BlockSampler):
    """The acting policy of a population, ``[R, obs] -> [R, D]`` in [-1, 1]: uniform random for
    the first ``warmup_blocks`` episodes, then SAC's policy sample tanh(loc + scale * n) or TD3's
    clip(mu + noise * n, -1, 1) (``noise`` set), with n ~ N(0, 1) from member r's generator.

    Noise is drawn an episode (``block`` steps) at a time per member (``BlockSampler``);
    ``blocks`` counts the episodes begun (saved by checkpoints: it decides the warm-up).
    With ``norm`` (``algo.td.observation_norm``) every observation it acts on (warm-up included, paused
    probes not) updates the running statistics, and the network sees it normalised."""

    def __init__(self, net: nn.Module, generators: Sequence[torch.Generator], action_dim: int, block: int,
                 warmup_blocks: int, noise: float | None = None, norm: ObservationNorm | None = None):
        super().__init__(net, generators, action_dim, block)
        self.warmup_blocks, self.noise, self.norm = warmup_blocks, noise, norm
        self.blocks = 0
        self._draws: torch.Tensor | None = None

    def deterministic(self, observation: torch.Tensor) -> torch.Tensor:
        out = self.net(self.norm(observation) if self.norm is not None else observation)
        return torch.tanh(out[0]) if isinstance(out, tuple) else out

    @torch.no_grad()
    def __call__(self, observation: torch.Tensor) -> torch.Tensor:
        if self._paused:
            return self.deterministic(observation)
        if self.norm is not None:
            self.norm.update(observation)
            observation = self.norm(observation)
        if self._step == self.block:
            warmup = self.blocks < self.warmup_blocks
            self._draws = torch.stack([
                torch.rand(self.block, self.action_dim, generator=g, device=g.device) * 2 - 1 if warmup
                else torch.randn(self.block, self.action_dim, generator=g, device=g.device) for g in self.generators])
            self._warmup, self._step = warmup, 0
            self.blocks += 1
        draw = self._draws[:, self._step]
        self._step += 1
        if self._warmup:
            return draw
        if self.noise is None:  # SAC: a sample of the tanh-squashed Gaussian
            loc, scale = self.net(observation)
            return torch.tanh(loc + scale * draw)
        return (self.net(observation) + self.noise * draw).clamp_(-1.0, 1.0)

    def state_dict(self) -> dict:
        if not self.at_block_boundary:
            raise RuntimeError("the acting policy's state is saved between episodes")
        state = {"blocks": self.blocks}
        if self.norm is not None:
            state["observation_norm"] = {k: v.clone() for k, v in self.norm.state_dict().items()}
        return state

    def load_state_dict(self, state: dict) -> None:
        if (self.norm is not None) != ("observation_norm" in state):
            raise ValueError("the checkpoint's acting policy " + ("lacks" if self.norm is not None else "has")
                             + " running observation statistics (algo.td.observation_norm differs)")
        if self.norm is not None:
            self.norm.load_state_dict(state["observation_norm"])
        self.blocks, self._step = int(state["blocks"]), self.block


def make_loss(cfg, networks: Networks, generators: Sequence[torch.Generator]):
    algo, td = cfg.algo, cfg.algo.td
    members, action_dim = len(generators), networks.sampler.action_dim
    spec = Bounded(-1.0, 1.0, (action_dim,), device=generators[0].device)
    # Eagerly, looping over the Q-networks is faster than vmap; compiled, the loop's pytree
    # bookkeeping would recompile the graph on every call, and vmap compiles into one graph.
    if algo.loss == "naf":
        loss = NAFLoss(networks.actor, networks.qvalues[0], action_dim, loss_function=td.loss_function)
    elif algo.loss == "trust_pcl":
        pcl = algo.trust_pcl
        loss = TrustPCLLoss(networks.actor, networks.qvalues[0], gamma=cfg.gamma, rollout=pcl.rollout,
                            entropy=pcl.entropy, max_divergence=pcl.max_divergence, clip=pcl.clip,
                            critic_weight=pcl.critic_weight, members=members, coefficient=pcl.initial_coefficient)
    elif algo.loss in ENTROPY_LOSSES:
        sac = algo.sac
        target_entropy = sac.target_entropy if sac.target_entropy is not None else -float(action_dim)
        common = dict(members=members, generators=generators, num_qvalue_nets=len(networks.qvalues),
                      alpha_init=sac.alpha_init, fixed_alpha=sac.fixed_alpha, target_entropy=target_entropy,
                      action_spec=spec, deactivate_vmap=not cfg.compile)
        if algo.loss == "sac":
            loss = MemberSACLoss(networks.actor, networks.qvalues, loss_function=td.loss_function, **common)
        elif algo.loss == "crossq":
            common["deactivate_vmap"] = True  # its batch norm updates running statistics in place
            loss = MemberCrossQLoss(networks.actor, networks.qvalues, loss_function=td.loss_function, **common)
        elif algo.loss == "redq":  # computed by losses.td.redq_losses (eager only)
            redq = algo.redq
            common["deactivate_vmap"] = True
            loss = MemberREDQLoss(networks.actor, networks.qvalues, loss_function=td.loss_function, subset=redq.subset,
                                  min_alpha=redq.min_alpha if redq.min_alpha is not None else 0.0,
                                  max_alpha=redq.max_alpha if redq.max_alpha is not None else math.inf, **common)
        else:  # tqc: its critic loss is the quantile Huber loss (td.loss_function smooth_l1, checked)
            loss = MemberTQCLoss(networks.actor, networks.qvalues,
                                 top_quantiles_to_drop_per_net=algo.tqc.drop_per_critic, **common)
    elif algo.loss == "td3":
        loss = MemberTD3Loss(networks.actor, networks.qvalues, spec, policy_noise=algo.td3.policy_noise,
                             noise_clip=algo.td3.noise_clip, loss_function=td.loss_function, generators=generators,
                             deactivate_vmap=not cfg.compile)
    else:
        raise unbuilt(algo.loss, "make_loss")
    loss.make_value_estimator(gamma=cfg.gamma)
    return loss.to(generators[0].device)


def critic_layout(loss) -> tuple[str, int]:
    """(name, member dimension) of the critic's parameters as ``loss`` holds them: TorchRL's ensembles of
    Q-networks ``qvalue_network`` stacked ``[Q-net, member, ...]``; a single critic (NAF's value
    network) ``value_network``, ``[member, ...]``. Its target network is ``target_<name>_params``."""
    return ("qvalue_network", 1) if hasattr(loss, "qvalue_network_params") else ("value_network", 0)


def critic_params(loss, target: bool = False) -> TensorDictBase:
    name, _ = critic_layout(loss)
    return getattr(loss, f"target_{name}_params" if target else f"{name}_params")


def make_optimisers(cfg, loss) -> Optimisers:
    """Adam over the actor's parameters (and SAC's per-member temperature) and over the critic's as
    the loss holds them (``critic_layout``)."""
    algo = cfg.algo
    actor = list(loss.actor_network_params.values(True, True))
    if isinstance(getattr(loss, "log_alpha", None), nn.Parameter):
        actor.append(loss.log_alpha)
    critic = [p for p in critic_params(loss).values(True, True) if p.requires_grad]  # not batch-norm statistics
    return Optimisers(
        actor=MemberAdam(actor, lr=algo.actor_lr, eps=algo.adam_eps),
        critic=MemberAdam(critic, lr=algo.critic_lr, eps=algo.adam_eps, member_dims=[critic_layout(loss)[1]] * len(critic),
                          weight_decay=algo.td.critic_weight_decay))


# Every loss TDPhaseRunner steps, with its diagnostics (metrics.csv's critic/... and actor/... columns).
STEPS = {"sac": (("loss_qvalue",), ("loss_actor", "loss_alpha", "alpha")),
         "tqc": (("loss_qvalue",), ("loss_actor", "loss_alpha", "alpha")),
         "crossq": (("loss_qvalue",), ("loss_actor", "loss_alpha", "alpha")),
         "redq": (("loss_qvalue",), ("loss_actor", "loss_alpha", "alpha")),
         "td3": (("loss_qvalue",), ("loss_actor",)),
         "naf": (("loss_qvalue", "value", "advantage"), ()),  # one loss trains mu, V and L
         "trust_pcl": (("loss_value", "consistency"), ("loss_actor", "lambda"))}


class MemberSoftUpdate(SoftUpdate):
    """TorchRL's ``SoftUpdate`` with its step in one ``torch._foreach_lerp_`` over every target tensor: the
    call TensorDict's ``lerp_`` makes per network (``target <- target + tau (online - target)``, pairing
    the tensors in ``_values_list`` order as it does), the same bits, without building a TensorDict of
    ``.data`` per network and step (about 1 ms a step at these sizes, a third of a small step)."""

    @torch.no_grad()
    def step(self) -> None:
        if not self.initialized:
            raise RuntimeError(f"{type(self).__name__} must be initialized (init_()) before step()")
        targets, sources = [], []
        for key, source in self._sources.items():
            target = self._targets.get(f"target_{key}")
            targets += target._values_list(True, True)
            sources += source._values_list(True, True)
        torch._foreach_lerp_(targets, sources, 1 - self.eps)


class TDPhaseRunner:
    """The gradient steps of SAC or TD3 before an episode (``run``), with ``PhaseRunner``'s
    interface (``active``, ``freeze``, the metrics' names)."""

    def __init__(self, cfg, loss, optimisers: Optimisers, generators: Sequence[torch.Generator],
                 memory=None, actor_net: nn.Module | None = None, qvalue_nets: Sequence[nn.Module] = (),
                 norm: ObservationNorm | None = None):
        """``memory``: the replay memory when its sampler is prioritised (else None). Each step's
        objective is compiled when ``cfg.compile`` (``learners.compiling``). The eager steps of SAC,
        TQC, CrossQ and TD3 compute on plain tensors (``losses.td.fused_*``: TorchRL's numbers, bit
        for bit) when ``FUSED`` and the actor network (``actor_net``) and Q-networks allow it.
        ``td.reset_every`` re-initialises the networks as they were built: the actor network (the
        loss's own) and the Q-networks ``qvalue_nets`` (whose fresh weights the loss's copies take).
        ``norm`` (``algo.td.observation_norm``): every minibatch's observations are normalised by the
        members' running statistics as they stand (the acting policy's, ``OffPolicySampler``).
        ``algo.sac.target_entropy_end``: the entropy target is set before each episode's steps."""
        self.loss, self.optimisers, self.generators = loss, optimisers, list(generators)
        self.kind, self.td = cfg.algo.loss, cfg.algo.td
        self.norm = norm
        self.entropy_schedule = None  # algo.sac.target_entropy_end: (episode, first, last) -> the entropy target
        if self.kind in ENTROPY_LOSSES and cfg.algo.sac.target_entropy_end is not None:  # from the loss's own start
            self.entropy_schedule = functools.partial(linear_schedule, float(loss.target_entropy),
                                                      cfg.algo.sac.target_entropy_end)
        self.episodes = cfg.episodes
        if self.kind not in STEPS:
            raise unbuilt(self.kind, "TDPhaseRunner")
        self.steps = cfg.env.episode_steps
        self.policy_delay = getattr(cfg.algo, self.kind).policy_delay if self.kind in ("td3", "crossq") else 1
        if self.kind == "redq":
            self.policy_delay = cfg.algo.redq.actor_every(self.td.updates_per_step)
        self.preact_penalty = (cfg.algo.td3.preact_penalty if self.kind == "td3"
                               else cfg.algo.naf.preact_penalty if self.kind == "naf" else 0.0)
        self.updater = MemberSoftUpdate(loss, tau=self.td.tau) if self.td.tau is not None else None  # crossq: none
        self.sampler = memory.sampler if memory is not None else None  # prioritised replay, or None
        self.active = torch.ones(len(self.generators), device=optimisers.critic.params[0].device)
        self.critic_metrics, self.actor_metrics = STEPS[self.kind]
        if self.kind == "trust_pcl":
            self.pcl, self.capacity = cfg.algo.trust_pcl, cfg.er.buffer_size
        self.actor_net, self.qvalue_nets = actor_net, list(qvalue_nets)
        if self.td.reset_every and (actor_net is None or not self.qvalue_nets):
            raise ValueError("td.reset_every needs the actor network and the Q-networks as built")
        available = {"sac": fused_sac_available, "td3": fused_td3_available, "tqc": fused_tqc_available,
                     "crossq": fused_crossq_available}.get(self.kind)  # others: no fused step
        why = ((f"{self.kind} has no fused step" if available is None else None)
               or ("learners.td.learner.FUSED is off" if not FUSED else None)
               or ("compile=true compiles the loss module's step" if cfg.compile else None)
               or ("the actor network was not given" if actor_net is None else None)
               or (None if available(loss, actor_net) else
                   f"the loss or its networks are not those losses.td's fused {self.kind} step computes"))
        self.fused = why is None
        # summary.json's record of the update path (engine.runner); REDQ computes by its own plain-tensor function
        path = "fused" if self.fused else "losses.td.redq_losses" if self.kind == "redq" else "loss module"
        self.path = {"critic": path, "actor": path, **({"why": why} if why and self.kind != "redq" else {})}
        self.code_refusal = None  # TorchRL's loss modules: the fused steps check their types (losses.td.fused_*_available)
        if self.kind == "redq" and (cfg.compile or actor_net is None or not redq_available(loss, actor_net)):
            raise ValueError("loss redq runs eagerly (compile=false) on the learner's own actor network and plain or "
                             "residual Q-networks (losses.td.redq_losses)")
        self._sac_objective = compile_step(self._sac_losses, cfg.compile)
        self._critic_objective = compile_step(self._td3_critic_losses, cfg.compile)
        self._actor_objective = compile_step(self._td3_actor_losses, cfg.compile)
        self._naf_objective = compile_step(self._naf_losses, cfg.compile)
        self._pcl_objective = compile_step(self._pcl_losses, cfg.compile)

    def normalised(self, batch: TensorDictBase) -> TensorDictBase:
        """``batch`` with its observations (and next observations) normalised (``norm``), or as it is."""
        if self.norm is not None:
            for key in ("observation", ("next", "observation")):
                batch.set(key, self.norm(batch.get(key)))
        return batch

    def set_target_entropy(self, episode: int) -> None:
        """``algo.sac.target_entropy_end``'s schedule: the entropy target before episode ``episode``'s steps,
        from the first episode with gradient steps to the last episode."""
        first = max(self.td.warmup_episodes, 1)
        self.loss.target_entropy.fill_(self.entropy_schedule(episode, first, self.episodes - 1))

    def updates(self, episode: int) -> tuple[int, int]:
        """(steps taken before, steps to take now) before episode ``episode``."""
        before = self.td.updates_before(episode - 1, self.steps) if episode > 0 else 0
        return before, self.td.updates_before(episode, self.steps) - before

    def run(self, data: TensorDictBase, minibatch_size: int, totals: MetricTotals, episode: int = 0) -> dict[int, str]:
        done, todo = self.updates(episode)
        if self.entropy_schedule is not None:
            self.set_target_entropy(episode)
        if self.td.reset_every and episode > 0 and episode % self.td.reset_every == 0:
            self.reset_networks()
        if self.kind == "trust_pcl":
            if todo:
                self._pcl_phase(data, minibatch_size, totals, episode, todo)
            return diverged_members(self.optimisers, totals, self.active)
        for step in range(done, done + todo):
            if self.sampler is not None:
                batch, index = prioritised_minibatch(data, minibatch_size, self.generators, self.sampler)
            else:
                batch = sample_minibatch(data, minibatch_size, self.generators)
            batch = self.normalised(batch)
            self.loss.draw(batch)  # the loss's noise, from each member's generator
            if self.kind == "crossq":
                priority = self._crossq_step(batch, step, totals)
            elif self.kind == "redq":
                priority = self._redq_step(batch, step, totals)
            elif self.kind == "naf":
                priority = self._naf_step(batch, totals)
            elif self.kind in ("sac", "tqc"):
                priority = self._sac_step(batch, totals)
            else:  # td3 (STEPS lists every loss with a step)
                priority = self._td3_step(batch, step, totals)
            if self.sampler is not None:
                self.sampler.update_priority(index.cpu(), priority.detach().cpu())
        return diverged_members(self.optimisers, totals, self.active)

    def _sac_losses(self, batch: TensorDictBase) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
        """SAC's three losses per member and the minibatch's priorities (TorchRL's loss writes them)."""
        if self.fused:
            fused = fused_tqc_losses if self.kind == "tqc" else fused_sac_losses
            return fused(self.loss, self.actor_net, batch)
        out = self.loss(batch)
        losses = {key: member_means(out[key]) for key in ("loss_qvalue", "loss_actor", "loss_alpha")}
        return losses, batch.get(PRIORITY_KEY)

    def _sac_step(self, batch: TensorDictBase, totals: MetricTotals) -> torch.Tensor:
        losses, priority = self._sac_objective(batch)
        self._minimise(sum(losses.values()), self.optimisers.critic, self.optimisers.actor)
        self.updater.step()
        totals.add("critic", {"loss_qvalue": losses["loss_qvalue"]})
        totals.add("actor", {"loss_actor": losses["loss_actor"], "loss_alpha": losses["loss_alpha"],
                             "alpha": self.loss.alpha})
        return priority

    def _naf_losses(self, batch: TensorDictBase) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
        """NAF's loss per member, its V and A means (diagnostics), the minibatch's priorities |y - Q|, and
        ``naf.preact_penalty`` x the mean square of mu's pre-tanh outputs (TD3's remedy for a policy stuck
        in tanh's flat tails; zero by default)."""
        out = self.loss(batch)
        losses = {key: member_means(out[key]) for key in ("loss_qvalue", "value", "advantage")}
        penalty = torch.zeros_like(losses["loss_qvalue"])
        if self.preact_penalty:
            penalty = self._preact(self.actor_net[0], batch)
        return losses, batch.get(PRIORITY_KEY), penalty

    def _naf_step(self, batch: TensorDictBase, totals: MetricTotals) -> torch.Tensor:
        """One step of NAF's one loss, which trains mu (the actor's optimiser) and V and L (the critic's)."""
        losses, priority, penalty = self._naf_objective(batch)
        self._minimise(losses["loss_qvalue"] + penalty if self.preact_penalty else losses["loss_qvalue"],
                       self.optimisers.critic, self.optimisers.actor)
        self.updater.step()
        totals.add("critic", losses)
        return priority

    def recent_returns(self, data: TensorDictBase, episode: int) -> list[list[float]]:
        """Each member's total rewards of the newest ``trust_pcl.divergence_episodes`` episodes of its memory
        ``data`` (``[R, n]``, slot order) before episode ``episode``: episodes 0 .. episode - 1 were written an
        episode at a time into a ring of whole episodes, so episode j sits in block j mod (capacity / steps)."""
        steps, (members, n) = self.steps, data.batch_size
        if n != min(episode * steps, self.capacity):
            raise ValueError(f"the memory holds {n} transitions before episode {episode}; trust_pcl expects every "
                             f"episode so far, {episode} x {steps} (at most its {self.capacity})")
        blocks = self.capacity // steps
        totals = data.get(("next", "reward")).reshape(members, n // steps, steps).double().sum(-1)
        newest = range(max(0, episode - self.pcl.divergence_episodes, episode - blocks), episode)
        index = torch.tensor([j % blocks for j in newest], device=totals.device)
        return totals[:, index].tolist()

    def _pcl_losses(self, batch: TensorDictBase) -> dict[str, torch.Tensor]:
        out = self.loss(batch)
        return {key: member_means(out[key]) for key in ("loss_actor", "loss_value", "consistency")}

    def _pcl_phase(self, data: TensorDictBase, minibatch_size: int, totals: MetricTotals, episode: int,
                   todo: int) -> None:
        """Trust-PCL's steps before an episode: the trust region's coefficient for each member from its newest
        episodes (``losses.trust_pcl.relative_entropy_coefficient``), then per step: lambda moves 1% towards it,
        a minibatch of sub-episodes, one step of both losses, the lagged networks follow by ``td.tau``."""
        targets = self.loss.coefficient_targets(self.recent_returns(data, episode), self.steps)
        for _ in range(todo):
            batch = self.normalised(sample_sub_episodes(data, minibatch_size, self.pcl.rollout, self.steps,
                                                        self.generators))
            self.loss.move_coefficient(targets)
            losses = self._pcl_objective(batch)
            self._minimise(losses["loss_actor"] + losses["loss_value"], self.optimisers.critic, self.optimisers.actor)
            self.updater.step()
            totals.add("critic", {"loss_value": losses["loss_value"], "consistency": losses["consistency"]})
            totals.add("actor", {"loss_actor": losses["loss_actor"], "lambda": self.loss.coefficient.float()})

    def _redq_step(self, batch: TensorDictBase, step: int, totals: MetricTotals) -> torch.Tensor:
        """A critic step of the ensemble; every ``policy_delay`` steps the same pass also gives the
        actor's and the temperature's losses (REDQ's one actor step per environment step at
        ``policy_delay = updates_per_step``)."""
        actor = (step + 1) % self.policy_delay == 0
        losses, priority = redq_losses(self.loss, self.actor_net, batch, actor=actor)
        if actor:
            self._minimise(sum(losses.values()), self.optimisers.critic, self.optimisers.actor)
            totals.add("actor", {"loss_actor": losses["loss_actor"], "loss_alpha": losses["loss_alpha"],
                                 "alpha": self.loss.alpha})
        else:
            self._minimise(losses["loss_qvalue"], self.optimisers.critic)
        self.updater.step()
        totals.add("critic", {"loss_qvalue": losses["loss_qvalue"]})
        return priority

    def _td3_critic_losses(self, batch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
        """TD3's Q loss per member and the minibatch's priorities (the largest error of the Q-networks;
        TorchRL's TD3 reports squared errors per Q-network)."""
        if self.fused:
            return fused_td3_critic_losses(self.loss, self.actor_net, batch)
        loss_qvalue, meta = self.loss.value_loss(batch)
        return member_means(loss_qvalue), meta["td_error"].max(0).values.sqrt()

    def _td3_actor_losses(self, batch: TensorDictBase) -> torch.Tensor:
        """TorchRL's actor loss -Q(s, mu(s)) per member, plus ``td3.preact_penalty`` x the mean
        square of the actor's pre-tanh outputs u(s) (mu = tanh(u)): a gradient that pulls u back
        from tanh's flat tails, where -Q's vanishes (TD3's collapse at full brake, docs/beyond.md)."""
        if self.fused:
            loss = fused_td3_actor_losses(self.loss, self.actor_net, batch)
        else:
            loss = member_means(self.loss.actor_loss(batch)[0])
        if self.preact_penalty:  # its own pass through the actor, as before the fused step (the same bits)
            loss = loss + self._preact(self.loss.actor_network.module.net[0], batch)
        return loss

    def _preact(self, body: nn.Module, batch: TensorDictBase) -> torch.Tensor:
        """The pre-tanh penalty per member (TD3's and NAF's): ``preact_penalty`` x the mean square of the
        actor's outputs before its tanh, ``body`` (``make_actor_net``'s first part), at the minibatch's states."""
        return self.preact_penalty * member_means(body(batch.get("observation")).square())

    def _td3_step(self, batch: TensorDictBase, step: int, totals: MetricTotals) -> torch.Tensor:
        loss_qvalue, priority = self._critic_objective(batch)
        self._minimise(loss_qvalue, self.optimisers.critic)
        totals.add("critic", {"loss_qvalue": loss_qvalue})
        if (step + 1) % self.policy_delay == 0:
            loss_actor = self._actor_objective(batch)
            self._minimise(loss_actor, self.optimisers.actor)
            self.updater.step()
            totals.add("actor", {"loss_actor": loss_actor})
        return priority

    def _crossq_step(self, batch: TensorDictBase, step: int, totals: MetricTotals) -> torch.Tensor:
        """A critic step (current and next state in one batch-normalised pass), then, every
        ``policy_delay`` steps, an actor and temperature step against the updated critics."""
        if self.fused:
            loss_qvalue, priority = fused_crossq_critic_losses(self.loss, self.actor_net, batch)
        else:
            loss_qvalue, meta = self.loss.qvalue_loss(batch)
            loss_qvalue, priority = member_means(loss_qvalue), meta["td_error"]
        self._minimise(loss_qvalue, self.optimisers.critic)
        totals.add("critic", {"loss_qvalue": loss_qvalue})
        if (step + 1) % self.policy_delay == 0:
            if self.fused:
                loss_actor, loss_alpha = fused_crossq_actor_losses(self.loss, self.actor_net, batch)
            else:
                loss_actor, actor_meta = self.loss.actor_loss(batch)
                loss_actor = member_means(loss_actor)
                loss_alpha = member_means(self.loss.alpha_loss(actor_meta["log_prob"]))
            self._minimise(loss_actor + loss_alpha, self.optimisers.actor)
            totals.add("actor", {"loss_actor": loss_actor, "loss_alpha": loss_alpha, "alpha": self.loss.alpha})
        return priority

    def _minimise(self, per_member: torch.Tensor, *optimisers: MemberAdam) -> None:
        for optimiser in optimisers:
            optimiser.zero_grad()
        (per_member * self.active).sum().backward()
        for optimiser in optimisers:
            optimiser.step()

    @torch.no_grad()
    def reset_networks(self) -> None:
        """BRO's periodic reset: every member's actor, Q-networks, target networks and temperature
        as at the start (new weights drawn from each member's generator in the order they were first
        drawn: actor, then the Q-networks one by one), and both optimisers restarted; the replay
        memory stays. Frozen members stay frozen (zero)."""
        reset_parameters(self.actor_net, self.generators)  # the loss's actor parameters themselves
        online, ensemble = critic_params(self.loss), critic_layout(self.loss)[1] == 1
        for i, q in enumerate(self.qvalue_nets):
            reset_parameters(q, self.generators)  # a single critic (NAF's): the loss's parameters themselves
            if ensemble:
                for name, value in q.state_dict().items():  # batch-norm statistics (CrossQ) too: never run, as built
                    online.get(("module", *name.split(".")))[i].copy_(value)
        name = critic_layout(self.loss)[0]
        pairs = [(f"{name}_params", f"target_{name}_params"),
                 ("actor_network_params", "target_actor_network_params")]
        for source, target in pairs:
            if hasattr(self.loss, target):
                getattr(self.loss, target).update_(getattr(self.loss, source).detach())
        if isinstance(getattr(self.loss, "log_alpha", None), torch.Tensor):
            self.loss.log_alpha.fill_(math.log(float(self.loss.alpha_init)))
        self.optimisers.actor.restart()
        self.optimisers.critic.restart()
        for member in self.active.eq(0).nonzero().flatten().tolist():
            self.freeze(member)

    def freeze(self, member: int) -> None:
        """As ``PhaseRunner.freeze``, target networks included."""
        self.active[member] = 0.0
        dim = critic_layout(self.loss)[1]
        targets = [(t, 0) for t in getattr(self.loss, "target_actor_network_params", {}).values(True, True)]
        targets += [(t, dim) for t in critic_params(self.loss, target=True).values(True, True)]
        targets += [(t, dim) for t in critic_params(self.loss).values(True, True)  # batch-norm statistics
                    if not t.requires_grad]
        freeze_member(self.optimisers, member, targets)

    def member_critic(self, member: int) -> dict[str, torch.Tensor]:
        """Member ``member``'s trained critic (an ensemble's: ``[Q-net, ...]`` per entry), on the CPU."""
        dim = critic_layout(self.loss)[1]
        return {k: v.select(dim, member).detach().cpu().clone()
                for k, v in critic_params(self.loss).flatten_keys(".").items()}


def build(cfg, env, generators: Sequence[torch.Generator], memory: ReplayMemory) -> Learner:
    """Networks, loss, optimisers and update phase of ``cfg.algo`` (an off-policy loss, ``learners.td.LOSSES``) for one
    member per generator."""
    networks = make_networks(cfg, env, generators)
    loss = make_loss(cfg, networks, generators)
    optimisers = make_optimisers(cfg, loss)
    phases = TDPhaseRunner(cfg, loss, optimisers, generators, memory if cfg.er.priority else None,
                           actor_net=networks.actor_net, qvalue_nets=networks.qvalue_nets, norm=networks.norm)
    keys = TD_TRANSITION_KEYS + tuple(k for key in critic_extras(cfg.algo.td) for k in (key, ("next", key)))
    return Learner(networks, loss, optimisers, memory, phases, keys, monte_carlo=False, n_step=cfg.algo.td.n_step)
