"""Every learner, declared once and found by name (``algo.loss``).

A learner is one module (``learners/<family>/<name>.py``) whose ``SPEC`` declares it: its name, how
tables title it, the family whose machinery runs it (``learners.monte_carlo``: the paper's phases on
Monte-Carlo returns; ``learners.td``: gradient steps per environment step on a replay memory), the
option blocks it reads (``algo.<block>``, each a frozen dataclass that checks its values where it is
declared), the rules it sets on the rest of a run's configuration, and the shape of its critic for
the memory estimate. The rest of the module is its torch half (networks, loss module, update step),
imported when a run builds it: this module, the specs and the options load without torch, so a run's
configuration is checked before torch loads.

The registry finds them itself: every module of ``learners/monte_carlo/`` and ``learners/td/`` whose
top level assigns ``SPEC`` is a learner (read from its source, so the families' torch machinery beside
them is not imported). ``spec(name)`` finds one; ``LEARNERS`` lists them all. Nothing else names a
learner: what differs between learners is an attribute of their spec or a function of their module,
never a comparison of ``algo.loss`` with a string (``tests/test_registry.py`` reads the code for one).
"""

from __future__ import annotations

import ast
import importlib
import importlib.util
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass, field

from learners.options import ConfigError

# The families, in the order tables list their learners; within one, learners by name. A learner is any
# module of a family's package whose top level assigns SPEC: adding one is its module, its
# conf/algo/<name>.yaml and its tests (docs/learners.md), no list to extend.
FAMILY_ORDER = ("monte_carlo", "td")


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
    pessimism: bool = False  # its target and actor combine the Q-networks by algo.td.pessimism (losses.td.q_reduce)
    target_networks: bool = True  # it keeps target networks (algo.td.tau); CrossQ does not
    prioritised: bool = True  # it can train on prioritised replay (off-policy learners: er=prioritised)
    rows: Callable = lambda algo, minibatch: minibatch  # rows a minibatch puts through a network (memory estimate)
    # its own networks' sizes where network.* does not shape them: (algo, obs, action) -> (parameters per member,
    # widest layer, layers) (memory estimate); None: network.actor_hidden and critic's MLPs
    networks: Callable | None = None
    acting: Callable = lambda algo, steps: 0  # floats its acting policy holds per member beyond the action (a
    #                                           planner's draws for an episode of `steps` and its samples' activations)

    def torch_half(self):
        """Its module (imports torch)."""
        return importlib.import_module(self.module)


def _declares_spec(name: str) -> bool:
    """Whether module ``name``'s top level assigns ``SPEC``, read from its source before importing it (the
    families' machinery beside the learners imports torch; a configuration is checked before torch loads)."""
    found = importlib.util.find_spec(name)
    source = found.loader.get_source(name) if found is not None and found.loader is not None else None
    if not source:
        return False
    for node in ast.parse(source, name).body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        if any(isinstance(t, ast.Name) and t.id == "SPEC" for t in targets):
            return True
    return False


def _modules() -> tuple[str, ...]:
    """Every learner's module: the modules of each family's package that declare a ``SPEC``."""
    found = []
    for family in FAMILY_ORDER:
        package = importlib.import_module(f"learners.{family}")
        names = sorted(info.name for info in pkgutil.iter_modules(package.__path__) if not info.ispkg)
        found += [f"learners.{family}.{name}" for name in names if _declares_spec(f"learners.{family}.{name}")]
    return tuple(found)


MODULES = _modules()


def required(protocol) -> list[str]:
    """The members a family's ``LearnerModule`` protocol declares: its annotated attributes and functions."""
    names = set(getattr(protocol, "__annotations__", {}))
    names |= {key for key, value in vars(protocol).items() if callable(value) and not key.startswith("_")}
    return sorted(names)


def check_module(module, family) -> None:
    """Refuse a learner module that lacks what its family's ``LearnerModule`` requires (or one of
    ``ONE_OF``), naming each missing member and where the interface is declared."""
    missing = [name for name in required(family.LearnerModule) if not hasattr(module, name)]
    if family.ONE_OF and not any(hasattr(module, name) for name in family.ONE_OF):
        missing.append(" or ".join(family.ONE_OF))
    if missing:
        raise RuntimeError(f"{module.__name__}: a learner of {family.__name__} needs {', '.join(missing)} "
                           f"({family.__name__}.LearnerModule declares each)")


def _load() -> dict[str, LearnerSpec]:
    specs = {}
    for name in MODULES:
        module = importlib.import_module(name)
        spec = module.SPEC
        if spec.module != name or f"learners.{spec.family}." not in name or spec.name in specs:
            raise RuntimeError(f"{name}: its SPEC must name this module (module=__name__), the family whose package "
                               "holds it, and a learner no other module names")
        check_module(module, importlib.import_module(f"learners.{spec.family}"))
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
