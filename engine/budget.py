"""The input budget: every value a tool's command line takes that sizes its memory or its time, bounded before
anything is allocated or run (torch-free).

- ``count(low, high)`` / ``real(low, high)``: an argparse ``type`` for a whole number / a finite number in
  ``[low, high]`` (``--episodes``, ``--processes``, ``--delta``); a value outside is argparse's one-line
  error naming the option, the range and what was given. A tool's command line declares each numeric
  option with one of these (``tests/test_layout.py`` fails a bare ``type=int`` or ``type=float`` in a tool);
- ``SEED``: a seed, in [0, 2**32);
- ``check_items(parser, option, values, most)``: a list option holds at most ``most`` values;
- ``check_work(parser, limit, what, **factors)``: the product that costs (episodes x tracks x runs, samples x
  iterations x horizon) at most ``limit``, each factor named in the one line that refuses it.

Training runs' own values are bounded where they are declared (``learners.options.capped``) and as the RAM they
add up to (``engine.limits.check_ram``); files by what their shapes may need (``engine.limits.weights_limit``).
"""

from __future__ import annotations

import argparse
import math


def count(low: int, high: int):
    """An argparse ``type``: a whole number in [``low``, ``high``]."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a whole number in [{low:,}, {high:,}], got {text[:40]!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be in [{low:,}, {high:,}], got {value:,}"[:200])
        return value

    parse.__name__ = "count"  # argparse names the type in its messages
    parse.bounds = (low, high)
    return parse


def real(low: float, high: float):
    """An argparse ``type``: a finite number in [``low``, ``high``]."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be a number in [{low:g}, {high:g}], got {text[:40]!r}") from None
        if not math.isfinite(value) or not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be a finite number in [{low:g}, {high:g}], got {text[:40]}")
        return value

    parse.__name__ = "number"
    parse.bounds = (low, high)
    return parse


SEED = count(0, 2**32 - 1)
EPISODES = count(1, 100_000)
PROCESSES = count(1, 64)
STEPS = count(1, 1_000_000)


def check_items(parser, option: str, values, most: int, unique: bool = False) -> None:
    """``parser.error`` in one line if the list ``option`` holds more than ``most`` values (or, ``unique``, one
    value twice: two jobs of one value would share their folder or their row)."""
    if values is None:
        return
    if len(values) > most:
        parser.error(f"{option} holds {len(values):,} values; it takes at most {most:,}")
    if unique and len(set(values)) < len(values):
        twice = next(v for v in values if values.count(v) > 1)
        parser.error(f"{option} names {twice} twice; name each once")


def check_work(parser, limit: int, what: str, **factors) -> None:
    """``parser.error`` in one line if the product of ``factors`` (the work the command would do, in ``what``)
    is above ``limit``."""
    total = math.prod(int(v) for v in factors.values())
    if total > limit:
        named = " x ".join(f"{v:,} {k.replace('_', ' ')}" for k, v in factors.items())
        parser.error(f"{named} is {total:,} {what}, more than a command does at once ({limit:,}); ask for fewer")
