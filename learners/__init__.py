"""Learners: each declared once in its own module and found by name (``learners.registry``); the
machinery they share in two families (``docs/learners.md`` adds one).

A family's ``__init__`` is torch-free, so a run's configuration is validated before torch
loads: ``KEYS`` and ``BLOCKS`` (the ``algo.*`` keys and option blocks every learner of the family
reads), ``check(algo, learner)``, ``OFF_POLICY`` (trains on a replay memory only) and
``build(cfg, env, generators, memory)``, which imports the family's torch half (``learner.py``)
and returns a ``learners.base.Learner``: the members' networks and acting policy, the loss, the
optimisers and the update phase the engine runs between episodes.

Shared below the families: ``base`` (the ``Learner`` record, divergence checks, metrics),
``networks`` (stacked member networks and samplers), ``optim`` (per-member Adam), ``solo`` (one
run's network layout, as saved and evaluated) and ``options`` (config checks).
"""

from __future__ import annotations

from learners import monte_carlo, td
from learners.registry import LEARNERS, in_family, spec  # noqa: F401  (in_family: the names of a family's learners)

FAMILIES = {"monte_carlo": monte_carlo, "td": td}
LOSSES = tuple(LEARNERS)  # every algo.loss value


def family(loss: str):
    """The family package whose machinery trains the learner ``loss`` (``learners.registry``)."""
    return FAMILIES[spec(loss).family]
