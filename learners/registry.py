"""Every learner, declared once and found by name (``algo.loss``).

A learner is one module (``learners/<family>/<name>.py``) whose ``SPEC`` declares it: its name, how
tables title it, the family whose machinery runs it (``learners.monte_carlo``: the paper's phases on
Monte-Carlo returns; ``learners.td``: gradient steps per environment step on a replay memory), the
option blocks it reads (``algo.<block>``, each a frozen dataclass that checks its values where it is
declared), the rules it sets on the rest of a run's configuration, and the shape of its critic for
the memory estimate. The rest of the module is its torch half (networks, loss module, update step),
imported when a run builds it: this module, the specs and the options load without torch, so a run's
configuration is checked before torch loads.

``spec(name)`` finds one; ``LEARNERS`` lists them all. Nothing else names a learner: what differs
between learners is an attribute of their spec or a function of their module, never a comparison
of ``algo.loss`` with a string (``tests/test_registry.py`` reads the code for one).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field

from learners.options import ConfigError

# The learners' modules, in the order tables list them. Adding a learner: its module (with SPEC),
# one line here, its conf/algo/<name>.yaml and its tests (docs/learners.md).
MODULES = ("learners.monte_carlo.ppo", "learners.monte_carlo.spg", "learners.td.sac", "learners.td.tqc",
           "learners.td.crossq", "learners.td.redq", "learners.td.td3", "learners.td.naf", "learners.td.trust_pcl")


def _nothing(*_) -> None:
    return None


@dataclass(frozen=True)
class LearnerSpec:
    """One learner, as its module declares it (torch-free)."""

    name: str  # its algo.loss value
    title: str  # how messages and tables name it
    family: str  # "monte_carlo" or "td": the package whose machinery trains it (learners.<family>)
    module: str  # its module: SPEC and its torch half
    blocks: dict = field(default_factory=dict)  # {block: options dataclass} of the algo.<block> it reads
    check: Callable = _nothing  # (algo) -> None: its rules on the algo's keys (ConfigError)
    check_run: Callable = _nothing  # (cfg) -> None: its rules on the rest of the run (er, env, compile)
    critic: Callable = lambda algo: (1, 1, True)  # (algo) -> (networks, outputs, reads the action): memory estimate
    gaussian_actor: bool = True  # its actor outputs a Gaussian's (loc, scale); else a tanh action
    past_critic: bool = False  # its steps feed the Q-networks the car's true state and past (algo.td.privileged_critic)
    target_networks: bool = True  # it keeps target networks (algo.td.tau); CrossQ does not
    prioritised: bool = True  # it can train on prioritised replay (off-policy learners: er=prioritised)
    rows: Callable = lambda algo, minibatch: minibatch  # rows a minibatch puts through a network (memory estimate)

    def torch_half(self):
        """Its module (imports torch)."""
        return importlib.import_module(self.module)


def _load() -> dict[str, LearnerSpec]:
    specs = {}
    for name in MODULES:
        spec = importlib.import_module(name).SPEC
        if spec.module != name or spec.name in specs:
            raise RuntimeError(f"{name}: its SPEC must name this module and a learner no other module names")
        specs[spec.name] = spec
    return specs


LEARNERS: dict[str, LearnerSpec] = _load()


def spec(name: str) -> LearnerSpec:
    """The learner ``algo.loss == name`` names; ConfigError listing every name otherwise."""
    try:
        return LEARNERS[name]
    except (KeyError, TypeError):
        raise ConfigError(f"algo.loss must be one of {', '.join(LEARNERS)}; got {name!r}") from None


def in_family(family: str) -> tuple[str, ...]:
    """The names of the learners the family ``family`` trains."""
    return tuple(name for name, s in LEARNERS.items() if s.family == family)
