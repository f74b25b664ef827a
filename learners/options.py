"""Typed option blocks and the checks every configuration class shares (torch-free).

A config node is a frozen dataclass built by ``build`` from a plain mapping (a node of the
Hydra config): every field required unless it has a default, no unknown keys, each value of
its declared type, and at most the ceiling its field declares (``capped``: every value that sets
an allocation has one, far above any use and below what would exhaust a machine by itself); rules
beyond types live in each class's ``__post_init__`` and fail with ``ConfigError``, one sentence naming
what was expected. The run's configuration
(``engine.config``) and each learner family's options (``learners.<family>``) are built so.
"""

from __future__ import annotations

import math
import typing
from collections.abc import Mapping
from dataclasses import MISSING, field, fields
from typing import Any, get_type_hints


ACTIVATIONS = ("tanh", "relu", "elu")  # the hidden activations the networks offer (learners.networks, learners.solo)


class ConfigError(ValueError):
    """A configuration value or combination that cannot be run."""


CEILING_NOTE = "conf/ documents each ceiling; they bound what a run allocates"


def capped(value: tuple[int, str] | None = None, length: tuple[int, str] | None = None, **kwargs) -> Any:
    """A dataclass field with ceilings ``build`` checks: ``value=(ceiling, what it counts)`` on the value
    (each value, for a list), ``length=(ceiling, what they count)`` on how many values a list holds. The
    rest of ``kwargs`` go to ``dataclasses.field`` (``default=``)."""
    return field(metadata={"ceilings": (value, length)}, **kwargs)


def ceilings(cls) -> dict[str, tuple[tuple[int, str] | None, tuple[int, str] | None]]:
    """``{field: (value ceiling, length ceiling)}`` of the fields of ``cls`` declared with ``capped``."""
    return {f.name: f.metadata["ceilings"] for f in fields(cls) if "ceilings" in f.metadata}


def _check_ceilings(where: str, value: Any, caps) -> None:
    on_value, on_length = caps
    if value is None:
        return
    several = isinstance(value, tuple)
    if on_length is not None and several and len(value) > on_length[0]:
        raise ConfigError(f"{where} holds {len(value):,} {on_length[1]}, above its ceiling of {on_length[0]:,} "
                          f"({CEILING_NOTE})")
    largest = max(value, default=None) if several else value
    if on_value is not None and largest is not None and largest > on_value[0]:
        said = f"has {largest:,} {on_value[1]}" if several else f"is {largest:,} {on_value[1]}"
        raise ConfigError(f"{where} {said}, above its ceiling of {on_value[0]:,} ({CEILING_NOTE})")


def build(cls, where: str, values: Mapping[str, Any]):
    """Instantiate dataclass ``cls`` from ``values``: every field required, no unknown keys."""
    names = [f.name for f in fields(cls)]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; valid keys are {names}")
    missing = [f.name for f in fields(cls) if f.name not in values and f.default is MISSING]
    if missing:
        raise ConfigError(f"{where}: missing key(s) {missing}")
    hints = get_type_hints(cls)
    caps = ceilings(cls)
    kwargs = {}
    for name in names:
        if name in values:
            kwargs[name] = coerce(f"{where}.{name}", values[name], hints[name])
            if name in caps:
                _check_ceilings(f"{where}.{name}", kwargs[name], caps[name])
    return cls(**kwargs)


FLOAT32_MAX = 3.4028234663852886e38  # the largest finite float32


def coerce(where: str, value: Any, hint: Any) -> Any:
    options = typing.get_args(hint)
    if type(None) in options and len(options) == 2 and not str(hint).startswith(("tuple", "dict")):
        if value is None:
            return None
        hint = next(o for o in options if o is not type(None))
    text = str(hint)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if text.startswith("tuple[int"):
        if value is None and "None" in text:
            return None
        if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__") or not all(
                isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in value):
            raise ConfigError(f"{where} must be a list of non-negative integers, got {value!r}")
        return tuple(value)
    if text.startswith("dict"):
        if value is None and "None" in text:
            return None
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where} must be a mapping, got {value!r}")
        return dict(value)
    return value


def choice(where: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"{where} must be one of {', '.join(choices)}; got {value!r}")


def _in_float32(where: str, value: float) -> None:
    if isinstance(value, float) and abs(value) > FLOAT32_MAX:
        raise ConfigError(f"{where} must be a number float32 holds (at most {FLOAT32_MAX:.4g}: the learners compute "
                          f"in float32), got {value!r}")


def positive(where: str, value: float) -> None:
    if not value > 0:
        raise ConfigError(f"{where} must be > 0, got {value!r}")
    _in_float32(where, value)


def at_least(where: str, value: float, low: float, note: str = "") -> None:
    if not value >= low:
        raise ConfigError(f"{where} must be >= {low}{note}, got {value}")
    _in_float32(where, value)
