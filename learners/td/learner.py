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
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import Bounded
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import SoftUpdate

from collectors import ReplayMemory, sample_minibatch
from learners import fast_paths
from learners.base import Learner, MetricTotals, Optimisers, diverged_members, freeze_member, prioritised_minibatch
from learners.networks import (BlockSampler, MemberNormalParamExtractor, NormalisedActor, ObservationNorm, StackedCriticNet,
                               StackedMLP, StackedResidualCriticNet, reset_parameters)
from learners.optim import MemberAdam
from learners.registry import spec as learner_spec
from learners.td import linear_schedule
from losses.td import ACTION_NOISE_KEY, CRITIC_EXTRAS, DrawnTanhNormal, member_means
from losses.functional import as_alone

FUSED = True  # the eager steps of SAC (DroQ, BRO), TQC, CrossQ and TD3 on plain tensors (losses.<name>.fused_*: the
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
        return as_alone(torch.tanh, x)  # each member's as alone (losses.functional.as_alone)


def make_actor_net(learner, members: int, obs_dim: int, action_dim: int, network, algo=None) -> nn.Module:
    """The members' stacked actor of ``learner`` (its ``learners.registry`` spec) with the run's ``network`` and
    ``algo`` settings (mappings or the run's config): the learner module's own ``actor_network`` where it has
    one; else an MLP of ``network.actor_hidden``, for a ``gaussian_actor`` (SAC's, TQC's, CrossQ's, REDQ's,
    Trust-PCL's) ``[R, ..., obs] -> (loc, scale)`` of a Gaussian (squashed by tanh when sampled), else (TD3's,
    NAF's) ``[R, ..., obs] -> tanh action``."""
    own = getattr(learner.torch_half(), "actor_network", None)
    if own is not None:
        return own(members, obs_dim, action_dim, network, algo)
    hidden, activation = _setting(network, "actor_hidden"), _setting(network, "activation")
    if learner.gaussian_actor:
        body = StackedMLP(members, [obs_dim, *hidden, 2 * action_dim], activation, linear_output=True)
        return nn.Sequential(body, MemberNormalParamExtractor(scale_lb=1e-4))
    body = StackedMLP(members, [obs_dim, *hidden, action_dim], activation, linear_output=True)
    return nn.Sequential(body, _Tanh())


def _setting(block, key: str):
    """``block``'s ``key``: a run's settings are mappings (``summary.json``), its configuration dataclasses."""
    return block[key] if isinstance(block, dict) else getattr(block, key)


def make_networks(cfg, env, generators: Sequence[torch.Generator]) -> Networks:
    """Actor, then the critic networks the learner builds (its module's ``critics``), each member's weights
    from its generator (Glorot, zero biases), in that order."""
    algo, net, members = cfg.algo, cfg.network, len(generators)
    learner = learner_spec(algo.loss)
    steps = learner.torch_half()
    obs_dim = env.observation_spec["observation"].shape[-1]
    action_dim = env.action_spec.shape[-1]
    device = generators[0].device
    actor_net = make_actor_net(learner, members, obs_dim, action_dim, net, algo).to(device)
    actor = steps.actor(actor_net)
    reset_parameters(actor_net, generators)
    norm = ObservationNorm(members, obs_dim).to(device) if algo.td.observation_norm else None
    extras = critic_extras(algo.td)
    inputs = Inputs(obs_dim, sum(env.observation_spec[key].shape[-1] for key in extras), action_dim, extras)
    qvalue_nets, qvalues = steps.critics(cfg, inputs, generators)
    sampler = OffPolicySampler(actor_net, generators, action_dim, block=cfg.env.episode_steps,
                               warmup_blocks=algo.td.warmup_episodes, noise=steps.exploration_noise(cfg), norm=norm)
    return Networks(actor_net, qvalue_nets, actor, qvalues, sampler, norm)


@dataclass(frozen=True)
class Inputs:
    """What the critics read: the observation's width, that of the extras (``critic_extras``: the car's true
    state and past, read besides (s, a)) and the action's; the extras' keys."""

    observation: int
    extras: int
    action: int
    extra_keys: list


def tanh_normal_actor(actor_net: nn.Module) -> nn.Module:
    """The TensorDict actor of the learners with a learned temperature (SAC, TQC, CrossQ, REDQ): a tanh-squashed
    Gaussian whose reparameterised draws use the noise the loss draws per member (``ACTION_NOISE_KEY``)."""
    return ProbabilisticActor(TensorDictModule(actor_net, ["observation"], ["loc", "scale"]),
                              in_keys={"loc": "loc", "scale": "scale", "noise": ACTION_NOISE_KEY},
                              distribution_class=DrawnTanhNormal,
                              distribution_kwargs={"low": -1.0, "high": 1.0}, return_log_prob=False)


def q_networks(cfg, inputs: Inputs, generators: Sequence[torch.Generator], count: int,
               outputs: int = 1) -> tuple[list[nn.Module], list[TensorDictModule]]:
    """``count`` Q-networks Q(s, [extras,] a) of ``outputs`` values each, built and initialised one after the
    other: BRO's residual, layer-normalised ones (``algo.td.critic_blocks``), else MLPs of
    ``network.critic_hidden`` (with DroQ's dropout and layer normalisation when asked); and their
    TensorDict modules (``state_action_value``)."""
    algo, net, members, device = cfg.algo, cfg.network, len(generators), generators[0].device
    width = inputs.observation + inputs.extras + inputs.action
    nets = []
    for _ in range(count):
        if algo.td.critic_blocks:  # BRO's residual, layer-normalised Q-network
            q = StackedResidualCriticNet(members, width, algo.td.critic_width or net.critic_hidden[0],
                                         algo.td.critic_blocks, algo.td.critic_activation or net.activation,
                                         outputs=outputs).to(device)
        else:
            q = StackedCriticNet(members, width, net.critic_hidden, net.activation, outputs=outputs,
                                 dropout=algo.td.critic_dropout, layer_norm=algo.td.critic_layer_norm,
                                 generators=generators).to(device)
        reset_parameters(q, generators)
        nets.append(q)
    return nets, q_modules(nets, inputs)


def q_modules(nets: list[nn.Module], inputs: Inputs) -> list[TensorDictModule]:
    keys = ["observation", *inputs.extra_keys, "action"]  # concatenated in this order
    return [TensorDictModule(q, keys, ["state_action_value"]) for q in nets]


def entropy_loss_options(cfg, networks: Networks, generators: Sequence[torch.Generator]) -> dict:
    """The settings every loss with a learned temperature takes (``algo.sac``), as TorchRL names them."""
    sac, action_dim = cfg.algo.sac, networks.sampler.action_dim
    target_entropy = sac.target_entropy if sac.target_entropy is not None else -float(action_dim)
    # Eagerly, looping over the Q-networks is faster than vmap; compiled, the loop's pytree
    # bookkeeping would recompile the graph on every call, and vmap compiles into one graph.
    return dict(members=len(generators), generators=generators, num_qvalue_nets=len(networks.qvalues),
                alpha_init=sac.alpha_init, fixed_alpha=sac.fixed_alpha, target_entropy=target_entropy,
                action_spec=action_spec(networks, generators), deactivate_vmap=not cfg.compile)


def action_spec(networks: Networks, generators: Sequence[torch.Generator]) -> Bounded:
    return Bounded(-1.0, 1.0, (networks.sampler.action_dim,), device=generators[0].device)


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
        return as_alone(torch.tanh, out[0]) if isinstance(out, tuple) else out

    @torch.no_grad()
    def __call__(self, observation: torch.Tensor) -> torch.Tensor:
        if self._paused:
            return self.deterministic(observation)
        if self.norm is not None:
            self.norm.update(observation)
            observation = self.norm(observation)
        if self._step == self.block:
            self._warmup = self.blocks < self.warmup_blocks
            self.draw_block()
            self._step = 0
            self.blocks += 1
        step = self._step
        self._step += 1
        if self._warmup:
            return self._draws[:, step]
        return self.act(observation, step)

    def draw_block(self) -> None:
        """An episode's draws per member (``_draws``, ``[R, block, ...]``): uniform actions in the warm-up, else
        the N(0, 1) draws ``act`` reads."""
        self._draws = torch.stack([
            torch.rand(self.block, self.action_dim, generator=g, device=g.device) * 2 - 1 if self._warmup
            else torch.randn(self.block, self.action_dim, generator=g, device=g.device) for g in self.generators])

    def act(self, observation: torch.Tensor, step: int) -> torch.Tensor:
        """The action at the episode's step ``step`` after the warm-up (``observation`` as the network sees it)."""
        draw = self._draws[:, step]
        if self.noise is None:  # SAC: a sample of the tanh-squashed Gaussian
            loc, scale = self.net(observation)
            return as_alone(torch.tanh, loc + scale * draw)
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
    """The learner's loss module (its module's ``loss``), with its value estimator, on the members' device."""
    loss = learner_spec(cfg.algo.loss).torch_half().loss(cfg, networks, generators)
    _own_parameters(getattr(loss, "qvalue_network_params", None))
    loss.make_value_estimator(gamma=cfg.gamma)
    return loss.to(generators[0].device)


def _own_parameters(params: TensorDictBase | None) -> None:
    """TorchRL's losses take a list of ONE Q-network as an expanded view of that network's parameters: not
    leaves, so an optimiser given them would see no gradient. Each becomes a parameter of its own, as the
    entries of a list of several Q-networks are (a learner with one Q-network: ``algo.simbav2.critics=1``)."""
    views = [] if params is None else [key for key, value in params.items(True, True) if not value.is_leaf]
    if not views:
        return
    params.unlock_()
    for key in views:
        value = params.get(key)
        params.set(key, nn.Parameter(value.detach().clone(), requires_grad=value.requires_grad))
    params.lock_()


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
    """The gradient steps of an off-policy learner before an episode (``run``), with ``PhaseRunner``'s
    interface (``active``, ``freeze``, the metrics' names). What a step is belongs to the learner's
    module (``steps``: its ``step``, or ``phase`` for a learner that draws its minibatches itself)."""

    def __init__(self, cfg, loss, optimisers: Optimisers, generators: Sequence[torch.Generator],
                 memory=None, actor_net: nn.Module | None = None, qvalue_nets: Sequence[nn.Module] = (),
                 norm: ObservationNorm | None = None):
        """``memory``: the replay memory when its sampler is prioritised (else None). Each step's
        objective is compiled when ``cfg.compile`` (``learners.compiling``). The eager steps of SAC,
        TQC, CrossQ and TD3 compute on plain tensors (``losses.sac``, ``tqc``, ``crossq``, ``td3``: TorchRL's numbers, bit
        for bit) when ``FUSED`` and the actor network (``actor_net``) and Q-networks allow it (the
        learner's ``fused_available``). ``td.reset_every`` re-initialises the networks as they were
        built: the actor network (the loss's own) and the Q-networks ``qvalue_nets`` (whose fresh
        weights the loss's copies take). ``norm`` (``algo.td.observation_norm``): every minibatch's
        observations are normalised by the members' running statistics as they stand (the acting
        policy's, ``OffPolicySampler``). ``algo.sac.target_entropy_end``: the entropy target is set
        before each episode's steps."""
        self.cfg, self.loss, self.optimisers, self.generators = cfg, loss, optimisers, list(generators)
        self.spec = learner_spec(cfg.algo.loss)
        self.steps_of = steps = self.spec.torch_half()
        self.td = cfg.algo.td
        self.norm = norm
        self.actor_held = False  # the actor's optimiser skips its steps (``run``: algo.td.critic_first_episodes)
        self.entropy_schedule = None  # algo.sac.target_entropy_end: (episode, first, last) -> the entropy target
        if cfg.algo.sac is not None and cfg.algo.sac.target_entropy_end is not None:  # from the loss's own start
            self.entropy_schedule = functools.partial(linear_schedule, float(loss.target_entropy),
                                                      cfg.algo.sac.target_entropy_end)
        self.episodes = cfg.episodes
        self.steps = cfg.env.episode_steps
        self.policy_delay = getattr(steps, "policy_delay", lambda cfg: 1)(cfg)
        self.preact_penalty = getattr(steps, "preact_penalty", lambda cfg: 0.0)(cfg)
        self.updater = MemberSoftUpdate(loss, tau=self.td.tau) if self.td.tau is not None else None  # crossq: none
        self.sampler = memory.sampler if memory is not None else None  # prioritised replay, or None
        self.active = torch.ones(len(self.generators), device=optimisers.critic.params[0].device)
        self.critic_metrics, self.actor_metrics = steps.METRICS
        self.actor_net, self.qvalue_nets = actor_net, list(qvalue_nets)
        if self.td.reset_every and (actor_net is None or not self.qvalue_nets):
            raise ValueError("td.reset_every needs the actor network and the Q-networks as built")
        available = getattr(steps, "fused_available", None)
        name = self.spec.name
        # the loss's own code (an edit, a method added, a subclass): said in one line (learners.fast_paths); read
        # only where the fused step could run
        self.code_refusal = None

        def code_refusal() -> str | None:
            self.code_refusal = fast_paths.refusal(loss)
            return self.code_refusal

        why = ((f"{name} has no fused step" if available is None else None)
               or ("learners.td.learner.FUSED is off" if not FUSED else None)
               or ("compile=true compiles the loss module's step" if cfg.compile else None)
               or ("the actor network was not given" if actor_net is None else None)
               or code_refusal()
               or (None if available(loss, actor_net) else
                   f"the loss or its networks are not those losses.{name}'s fused step computes"))
        if why != self.code_refusal:
            self.code_refusal = None  # said only where it is what keeps the fused step off
        self.fused = why is None
        # summary.json's record of the update path (engine.runner)
        self.fast_path_code = (f"losses.{name}.fused_",)  # its fused step's own functions (learners.fast_paths)
        path = "fused" if self.fused else "loss module"
        self.path = {"critic": path, "actor": path, **({"why": why} if why else {})}
        steps.prepare(self)  # its compiled objectives and any check of what was built

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
        self.actor_held = episode <= self.td.critic_first_episodes  # the steps on its first episodes: critics only
        if self.entropy_schedule is not None:
            self.set_target_entropy(episode)
        if self.td.reset_every and episode > 0 and episode % self.td.reset_every == 0:
            self.reset_networks()
        before = getattr(self.steps_of, "before_steps", None)
        if before is not None and todo:  # what the learner sets from the memory before its steps (SimbaV2's reward scale)
            before(self, data)
        phase = getattr(self.steps_of, "phase", None)
        if phase is not None:  # a learner that draws its own minibatches (Trust-PCL's sub-episodes)
            if todo:
                phase(self, data, minibatch_size, totals, episode, todo)
            return diverged_members(self.optimisers, totals, self.active)
        for step in range(done, done + todo):
            if self.sampler is not None:
                batch, index = prioritised_minibatch(data, minibatch_size, self.generators, self.sampler)
            else:
                batch = sample_minibatch(data, minibatch_size, self.generators)
            batch = self.normalised(batch)
            self.loss.draw(batch)  # the loss's noise, from each member's generator
            priority = self.steps_of.step(self, batch, step, totals)
            if self.sampler is not None:
                self.sampler.update_priority(index.cpu(), priority.detach().cpu())
        return diverged_members(self.optimisers, totals, self.active)

    def preact(self, body: nn.Module, batch: TensorDictBase) -> torch.Tensor:
        """The pre-tanh penalty per member (TD3's and NAF's): ``preact_penalty`` x the mean square of the
        actor's outputs before its tanh, ``body`` (``make_actor_net``'s first part), at the minibatch's states."""
        return self.preact_penalty * member_means(body(batch.get("observation")).square())

    def minimise(self, per_member: torch.Tensor, *optimisers: MemberAdam) -> None:
        """One step of ``optimisers`` on the active members' losses; the actor's (actor and temperature) is
        skipped while ``actor_held`` (``algo.td.critic_first_episodes``)."""
        for optimiser in optimisers:
            optimiser.zero_grad()
        (per_member * self.active).sum().backward()
        for optimiser in optimisers:
            if not (self.actor_held and optimiser is self.optimisers.actor):
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


def gaussian_mean(state: dict[str, torch.Tensor], last: str, rows: int) -> dict[str, torch.Tensor]:
    """A Gaussian actor's weights as the deterministic actor of its mean: the output layer ``last`` (its
    ``.weight``'s name) keeps its first ``rows`` rows, the mean's (the scale's follow them)."""
    bias = last.removesuffix("weight") + "bias"
    return {k: (v[:rows] if k in (last, bias) else v) for k, v in state.items()}


@torch.no_grad()
def start_actors(actor_net: nn.Module, starts: Sequence[dict]) -> None:
    """Write each member's start (``engine.start.start_actors``: an actor's weights under a solo actor's names)
    into the members' stacked actor ``actor_net``. A Gaussian actor's weights (its output layer's rows: the
    mean's, then the scale's) start a deterministic actor (half as many output rows) with the mean's rows: tanh
    of the mean, the Gaussian's deterministic policy, is then its action. ``ValueError`` on any other mismatch."""
    own = actor_net.state_dict()
    last = max((k for k in own if k.endswith(".weight")), key=list(own).index)  # the output layer
    rows = own[last].shape[1]
    for member, start in enumerate(starts):
        state = start["state"]
        if set(state) != set(own):
            raise ValueError(f"algo.td.start_from: the start's actor has entries {sorted(state)}, this run's {sorted(own)}")
        given = state[last].shape[0]
        if given == 2 * rows:  # a Gaussian's mean starts a deterministic actor
            state = gaussian_mean(state, last, rows)
        elif 2 * given == rows:
            raise ValueError("algo.td.start_from: a deterministic actor has no scale to start a Gaussian actor's from")
        for name, value in state.items():
            if value.shape != own[name].shape[1:]:
                raise ValueError(f"algo.td.start_from: the start's actor has {name} of shape {list(value.shape)}, this run's "
                                 f"{list(own[name].shape[1:])}")
            own[name][member].copy_(value.to(own[name].device))


@torch.no_grad()
def start_critics(loss, starts: Sequence[dict]) -> None:
    """Write each member's start critics (``critic.pt``: the Q-networks as ``member_critic`` saves them) into
    the loss's Q-networks and their target networks. ``ValueError`` if they are not this learner's shapes."""
    name, dim = critic_layout(loss)
    tables = [critic_params(loss).flatten_keys(".")]
    if hasattr(loss, f"target_{name}_params"):
        tables.append(critic_params(loss, target=True).flatten_keys("."))
    for member, start in enumerate(starts):
        state = start["critic"]
        own = tables[0]
        if set(state) != set(own.keys()):
            raise ValueError(f"algo.td.start_critics_from: the start's critic has entries {sorted(state)}, this run's "
                             f"{sorted(own.keys())}")
        for key, value in state.items():
            for table in tables:
                target = table.get(key).select(dim, member)
                if value.shape != target.shape:
                    raise ValueError(f"algo.td.start_critics_from: the start's critic has {key} of shape "
                                     f"{list(value.shape)}, this run's "
                                     f"{list(target.shape)}")
                target.copy_(value.to(target.device))


def build(cfg, env, generators: Sequence[torch.Generator], memory: ReplayMemory,
          starts: Sequence[dict] | None = None) -> Learner:
    """Networks, loss, optimisers and update phase of ``cfg.algo`` (an off-policy learner of ``learners.registry``)
    for one member per generator; ``starts`` (``engine.start``): each member's actor starts from other weights,
    written before the loss copies them into any target network, and its critics too where they are given."""
    networks = make_networks(cfg, env, generators)
    if starts is not None:
        start_actors(networks.actor_net, starts)
    loss = make_loss(cfg, networks, generators)
    own = getattr(learner_spec(cfg.algo.loss).torch_half(), "acting_policy", None)
    if own is not None:  # an acting policy that reads the trained loss (a planner: its model and Q-networks)
        networks.sampler = own(cfg, networks, loss)
    optimisers = make_optimisers(cfg, loss)
    phases = TDPhaseRunner(cfg, loss, optimisers, generators, memory if cfg.er.priority else None,
                           actor_net=networks.actor_net, qvalue_nets=networks.qvalue_nets, norm=networks.norm)
    if starts is not None and starts[0]["critic"] is not None:  # once the target updater is TorchRL's to know
        start_critics(loss, starts)
    keys = TD_TRANSITION_KEYS + tuple(k for key in critic_extras(cfg.algo.td) for k in (key, ("next", key)))
    return Learner(networks, loss, optimisers, memory, phases, keys, monte_carlo=False, n_step=cfg.algo.td.n_step)
