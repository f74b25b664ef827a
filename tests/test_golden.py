"""Golden runs: short training runs whose metrics.csv is checked to the bit.

A change meant to keep results unchanged (a refactor, a speed-up, a new code path) must leave
these files identical. They were recorded in the default numerics mode, ``fma``
(``engine/numerics.py``), with the software in ``fingerprint.json``, so they are checked to the
bit on every x86-64 CPU with AVX2. Under other software, or another mode or kernel set (native numerics on an AVX-512
CPU, a CPU without AVX2, ARM), kernels round differently, and the values are compared to a
relative tolerance instead. A change that is meant to change results regenerates them, and
says so in its commit:

    python -m tests.test_golden --update
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path

import pytest

GOLDEN = Path(__file__).resolve().parent / "golden"
RUNS = {  # name: overrides; together they cover both losses, all three replay modes, both epoch settings
    "spg_p_multi-hybrid": ["algo=spg_p_multi", "er=hybrid"],
    "spg-memory": ["algo=spg", "er=memory"],
    "ppo-recent": ["algo=ppo", "er=recent"],
    "ppo_log-memory": ["algo=ppo_log", "er=memory"],
}
COMMON = ["seed=2067791", "episodes=4", "progress=false", "logger=none", "checkpoint_every=0"]


def fingerprint() -> dict:
    from engine import numerics
    from engine.version import software_versions

    versions, effect = software_versions(), numerics.in_effect()
    return {"torch": versions["torch"], "numpy": versions["numpy"], "numerics": effect["mode"],
            "kernels": effect["kernels"], "mkl_branch": effect["mkl_branch"]}


def run(name: str, out_dir: Path) -> bytes:
    from engine.config import RunConfig
    from engine.runner import train

    train(RunConfig.compose(*RUNS[name], *COMMON), out_dir)
    return (out_dir / "metrics.csv").read_bytes()


def _rows(data: bytes) -> list[dict]:
    return list(csv.DictReader(data.decode().splitlines()))


@pytest.mark.parametrize("name", sorted(RUNS))
def test_golden_run(tmp_path, name):
    expected = (GOLDEN / f"{name}.csv").read_bytes()
    got = run(name, tmp_path)
    recorded = json.loads((GOLDEN / "fingerprint.json").read_text())
    if recorded == fingerprint():
        assert got == expected, (f"{name}: metrics.csv differs from tests/golden/{name}.csv; if the change is "
                                 "meant to change results, regenerate with python -m tests.test_golden --update")
        return
    for mine, theirs in zip(_rows(got), _rows(expected), strict=True):  # another build or CPU
        assert mine.keys() == theirs.keys()
        for key, value in theirs.items():
            if value:
                assert math.isclose(float(mine[key]), float(value), rel_tol=1e-3, abs_tol=1e-3), (name, key)


def update() -> None:
    import tempfile

    GOLDEN.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for name in sorted(RUNS):
            (GOLDEN / f"{name}.csv").write_bytes(run(name, Path(tmp) / name))
            print(f"wrote tests/golden/{name}.csv")
    (GOLDEN / "fingerprint.json").write_text(json.dumps(fingerprint(), indent=2) + "\n")


if __name__ == "__main__":
    import os

    os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
    if sys.argv[1:] != ["--update"]:
        raise SystemExit("usage: python -m tests.test_golden --update")
    from engine import numerics

    numerics.apply(numerics.DEFAULT)  # before torch loads
    update()
