"""``SPGLoss``: Sampled Policy Gradient with a Monte-Carlo Q(s, a) critic, optionally prioritised."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import ProbabilisticTensorDictSequential, TensorDictModule

from losses import functional as F
from losses.common import PhaseLoss, _members

BASELINES = ("mean", "action")
NOISE_KEY = "spg_noise"  # the perturbations of a minibatch, when drawn ahead of the loss (``SPGLoss.draw``)


class SPGLoss(PhaseLoss):
    """Sampled Policy Gradient: move the policy towards the best action the critic can find.

    For each state of a minibatch the candidates are the stored action, the policy mean and
    ``num_samples`` perturbations clip(centre + N(0, T^2 I), -1, 1); the critic scores all of
    them in one call and the best one is the target. The actor maximises mean log pi(target | s);
    prioritised (SPG-p) weights each state's term by Q(s, target) - Q(s, baseline).

    Args:
        actor_network: a probabilistic actor whose ``get_dist`` gives the policy and whose
            distribution has a ``mean``.
        qvalue_network: writes Q(s, a) to the ``state_action_value`` key.
        num_samples: K perturbed candidates per state.
        temperature: initial exploration temperature T (standard deviation of the perturbations).
        temperature_decay: T is multiplied by (1 - temperature_decay) after every actor phase.
        prioritised: weight by the Q gain of the target over the baseline (SPG-p).
        sample_around: centre of the perturbations, ``"mean"`` (reference) or ``"action"``
            (the paper's text: around the stored action).
        baseline: SPG-p's baseline, ``"mean"`` (reference) or ``"action"`` (paper's text).
        entropy_coeff: optional entropy bonus (0 in the paper).
        joint_log_prob: sum log-probabilities over action dimensions instead of averaging them.
        members: None, or the size R of a population (see ``losses.common.PhaseLoss``): then
            each member has its own temperature, and its perturbations come from its own
            generator (``set_generators``).

    Input keys: the actor's and critic's inputs, ``action`` and ``value_target`` (the
    Monte-Carlo return G, for the critic); optionally ``spg_noise`` (``draw``), else the actor's
    loss draws its perturbations itself.
    """

    @dataclass
    class _AcceptedKeys:
        action: str = "action"
        value_target: str = "value_target"

    actor_network: ProbabilisticTensorDictSequential
    qvalue_network: TensorDictModule
    actor_metrics = ("loss_objective", "loss_entropy", "entropy", "weight_mean", "q_target",
                     "q_gain", "target_is_action", "target_is_mean", "temperature")
    critic_attr = "qvalue_network"

    def __init__(self, actor_network: ProbabilisticTensorDictSequential, qvalue_network: TensorDictModule,
                 *, num_samples: int = 5, temperature: float = 1.0, temperature_decay: float = 0.01,
                 prioritised: bool = False, sample_around: str = "mean", baseline: str = "mean",
                 entropy_coeff: float = 0.0, joint_log_prob: bool = False, members: int | None = None):
        super().__init__()
        self.members = _members(members)
        if sample_around not in F.SAMPLE_CENTRES:
            raise ValueError(f"sample_around must be one of {F.SAMPLE_CENTRES}, got {sample_around!r}")
        if baseline not in BASELINES:
            raise ValueError(f"baseline must be one of {BASELINES}, got {baseline!r}")
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 0:
            raise ValueError(f"num_samples must be an integer >= 0, got {num_samples!r}")
        if not temperature >= 0 or not 0 <= temperature_decay < 1:
            raise ValueError(f"need temperature >= 0 and temperature_decay in [0, 1), got "
                             f"{temperature!r} and {temperature_decay!r}")
        self.actor_network = actor_network
        self.qvalue_network = qvalue_network
        self.num_samples = num_samples
        self.temperature_decay = float(temperature_decay)
        self.prioritised = bool(prioritised)
        self.sample_around = sample_around
        self.baseline = baseline
        self.entropy_coeff = float(entropy_coeff)
        self.joint_log_prob = bool(joint_log_prob)
        # A buffer, so that it travels with state_dict() (checkpoints) and .to(device).
        shape = () if members is None else (members,)
        self.register_buffer("temperature", torch.full(shape, float(temperature), dtype=torch.float64))
        self.generators: list[torch.Generator] | None = None

    def set_generators(self, generators: list[torch.Generator] | None) -> None:
        """Draw member r's perturbations from ``generators[r]`` (None: torch's global generator)."""
        if generators is not None and len(generators) != (self.members or 1):
            raise ValueError(f"got {len(generators)} generators for {self.members or 1} members")
        self.generators = generators

    def _noise(self, shape: torch.Size, like: torch.Tensor) -> torch.Tensor:
        if self.generators is None:
            return torch.randn(shape, dtype=like.dtype, device=like.device)
        if self.members is None:
            return torch.randn(shape, dtype=like.dtype, device=like.device, generator=self.generators[0])
        return torch.stack([torch.randn(shape[1:], dtype=like.dtype, device=like.device, generator=g)
                            for g in self.generators])

    def _perturbations(self, like: torch.Tensor) -> torch.Tensor:
        """N(0, I) noise for ``num_samples`` candidates per state of ``like`` (``[..., B, D]``)."""
        return self._noise(like.shape[:-1] + (self.num_samples, like.shape[-1]), like)

    def draw(self, tensordict: TensorDictBase) -> None:
        """Draw the perturbations of ``tensordict``'s states into it (``spg_noise``), as ``actor_loss``
        would: so that a compiled ``actor_loss`` does not call the generators."""
        tensordict.set(NOISE_KEY, self._perturbations(tensordict[self.tensor_keys.action]))

    # ------------------------------------------------------------------ phase preparation
    # Nothing to precompute before a phase: SPG scores candidates per minibatch.
    def after_actor_phase(self) -> None:
        """Cool the exploration temperature: T <- T * (1 - temperature_decay)."""
        self.temperature.mul_(1.0 - self.temperature_decay)

    # ---------------------------------------------------------------------------- losses
    def actor_loss(self, tensordict: TensorDictBase) -> TensorDictBase:
        keys = self.tensor_keys
        dist = self._policy(tensordict)
        action = tensordict[keys.action]
        with torch.no_grad():
            mean = dist.mean
            noise = tensordict.get(NOISE_KEY, None)
            if noise is None:
                noise = self._perturbations(mean)
            temperature = (self.temperature.item() if self.members is None
                           else self.temperature.to(mean.dtype).reshape(-1, *[1] * (noise.dim() - 1)))
            candidates = F.spg_candidates(action, mean, noise, temperature, self.sample_around)
            scores = self._score(tensordict, candidates)
            target, index = F.best_candidate(candidates, scores)
            q_target = scores.gather(-1, index.unsqueeze(-1))
            q_baseline = scores[..., 1:2] if self.baseline == "mean" else scores[..., 0:1]
            weight = q_target - q_baseline if self.prioritised else None
        log_prob = F.per_dimension_or_joint(dist.log_prob(target), self.joint_log_prob)
        entropy, entropy_term = self._entropy(dist)
        return TensorDict({
            "loss_objective": -F.weighted_log_likelihood(log_prob, weight, self.members is not None),
            "loss_entropy": entropy_term,
            "entropy": entropy,
            "weight_mean": torch.ones(q_target.shape[:-2]) if weight is None else self._mean(weight),
            "q_target": self._mean(q_target),
            "q_gain": self._mean(q_target - q_baseline),
            "target_is_action": self._mean((index == 0).float()),
            "target_is_mean": self._mean((index == 1).float()),
            "temperature": self.temperature.float(),
        })

    def _score(self, tensordict: TensorDictBase, candidates: torch.Tensor) -> torch.Tensor:
        """Q(s, c) for every candidate c, in one critic call: [..., B, C]."""
        count = candidates.shape[-2]
        keys = self.tensor_keys
        pairs = TensorDict({key: _repeat(tensordict[key], count)
                            for key in self.qvalue_network.in_keys if key != keys.action},
                           batch_size=candidates.shape[:-1])
        pairs.set(keys.action, candidates)
        return self._value(pairs).squeeze(-1)


def _repeat(value: torch.Tensor, count: int) -> torch.Tensor:
    """[..., B, F] -> [..., B, count, F] without copying."""
    return value.unsqueeze(-2).expand(*value.shape[:-1], count, value.shape[-1])
