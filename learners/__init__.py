"""Learners: one package per family, all of one shape (``docs/learners.md`` adds one).

A family's ``__init__`` is torch-free, so a run's configuration is validated before torch
loads: ``LOSSES`` (the ``algo.loss`` values it serves), ``KEYS`` and ``BLOCKS`` (the ``algo.*``
keys and option dataclasses it reads), ``check(algo)``, ``OFF_POLICY`` (trains on a replay
memory only) and ``build(cfg, env, generators, memory)``, which imports the family's torch half
(``learner.py``) and returns a ``learners.base.Learner``: the members' networks and acting
policy, the loss, the optimisers and the update phase the engine runs between episodes.

Shared below the families: ``base`` (the ``Learner`` record, divergence checks, metrics),
``networks`` (stacked member networks and samplers), ``optim`` (per-member Adam), ``solo`` (one
run's network layout, as saved and evaluated) and ``options`` (config checks).
"""

from __future__ import annotations

from learners import monte_carlo, td
from learners.options import ConfigError

FAMILIES = (monte_carlo, td)
LOSSES = tuple(loss for family_ in FAMILIES for loss in family_.LOSSES)


def family(loss: str):
    """The family package that serves ``algo.loss == loss``."""
    for family_ in FAMILIES:
        if loss in family_.LOSSES:
            return family_
    raise ConfigError(f"algo.loss must be one of {', '.join(LOSSES)}; got {loss!r}")
