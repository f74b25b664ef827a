"""Shared fixtures: the reference data in ../shared (skipped with a reason when absent); the
default numerics mode (``engine.numerics``), set before any test module loads torch."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # rendering tests run without a screen
os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

from engine import numerics  # noqa: E402

numerics.apply(numerics.DEFAULT)  # the tests run the default numerics; it must precede torch's import

from learners import kernels  # noqa: E402

_FMA_AT_START = kernels.active()  # the project's products run (a machine without a compiler runs portable)


@pytest.fixture(autouse=True)
def _default_numerics_after_each_test():
    """A test that ran report.py or evaluate.py in-process on portable runs switched this process to
    their mode; the next test (of any file, on the same worker) starts in the default again."""
    yield
    if _FMA_AT_START and not kernels.active():
        numerics.apply(numerics.DEFAULT)

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("RACING_SHARED_DIR", ROOT.parent / "shared"))
CONFORMANCE = SHARED / "reference" / "env_conformance.json"


def load_conformance() -> dict:
    if not CONFORMANCE.is_file():
        pytest.skip(f"conformance vectors not found at {CONFORMANCE} "
                    "(set RACING_SHARED_DIR to the folder holding reference/env_conformance.json)")
    return json.loads(CONFORMANCE.read_text())


@pytest.fixture(scope="session")
def conformance() -> dict:
    return load_conformance()


def pytest_collection_modifyitems(config, items):
    """The heaviest test files first (``heaviest_files_first``). Slow tests (over two seconds) carry
    ``@pytest.mark.slow`` themselves; ``pytest -m "not slow"`` is the quick tier."""
    items[:] = heaviest_files_first(items)


HEAVY_LIST = Path(__file__).with_name("heavy_files.txt")


def heaviest_files_first(items: list) -> list:
    """The tests grouped by file as collected, the files of tests/heavy_files.txt first in its order (the
    longest first), the others after them as collected. pytest-xdist (``--dist loadfile
    --no-loadscope-reorder``) hands the files to its workers in this order: the longest start first and
    the short ones fill in at the end, instead of a long file starting last and running alone."""
    lines = [line.split() for line in HEAVY_LIST.read_text().splitlines()]
    rank = {line[-1]: i for i, line in enumerate(line for line in lines if line and not line[0].startswith("#"))}
    files: dict[str, list] = {}
    for item in items:
        files.setdefault(item.nodeid.split("::")[0], []).append(item)
    ranked = sorted(enumerate(files), key=lambda pair: (rank.get(pair[1], len(rank)), pair[0]))
    return [item for _, name in ranked for item in files[name]]
