"""The exact-numerics promise on another vendor's CPU: a run here equals the same run on QEMU's emulated
AMD EPYC (``tests/cross_cpu.py``). Its own file, so that the slow emulation runs beside the other
test files rather than behind them (pytest-xdist hands out whole files)."""

from __future__ import annotations

import platform
import shutil

import pytest


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("qemu-x86_64") is None or platform.machine() != "x86_64",
                    reason="needs qemu-x86_64 (apt install qemu-user) on an x86-64 machine to emulate another CPU")
def test_default_numerics_runs_are_the_same_on_an_emulated_amd_cpu():
    """One short PPO run (numerics=fma, the default) here and on QEMU's AMD EPYC (AVX2, another vendor: MKL's other code paths);
    episodes of 64 steps (one minibatch), as emulation is slow."""
    from tests import cross_cpu

    assert cross_cpu.main(["--cpus", "EPYC-Rome", "--cells", "ppo_log/recent", "--episodes", "1",
                           "--max-steps", "64"]) == 0
