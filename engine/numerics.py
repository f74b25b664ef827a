"""Which floating-point kernels a process runs: the same on every x86-64 CPU, or the machine's own.

torch picks its element-wise and reduction kernels by the CPU's widest vector instructions
(AVX2 or AVX-512: ``torch.backends.cpu.get_cpu_capability()``), and MKL, which serves its
matrix products and some element-wise math, picks code paths by CPU too. The paths round
differently, so the same run gives other numbers on another CPU, and training is chaotic
enough that a last-bit difference grows into another learning curve.

Three modes (``numerics=`` in ``conf/config.yaml``):

- ``fma`` (the default): ``portable``'s torch and MKL settings, and the stacked layers' matrix
  products (forward, both gradients) computed by the project's own kernels
  (``learners.kernels``), in which every output element is one fixed chain of fused
  multiply-adds: the same bits on every CPU with FMA, at the speed of the CPU's widest vectors
  (MKL's COMPATIBLE branch runs them with SSE2 code). The kernels are compiled on first use;
  where no C++ compiler works, the mode runs ``portable`` instead, warns once and records why.
- ``portable``: torch runs its AVX2 kernels (``ATEN_CPU_CAPABILITY=avx2``) and MKL its
  conditional-numerical-reproducibility code path for every x86-64 CPU, Intel or not
  (``MKL_CBWR=COMPATIBLE``). A run gives the same ``metrics.csv`` on any x86-64 CPU with AVX2
  (with the same software and thread count). CPUs without AVX2 and other architectures (ARM)
  cannot run those kernels: there the mode runs the machine's own, and says so once.
- ``native``: whatever torch and MKL choose on this machine (the two variables unset): the
  fastest, reproducible on CPUs of the same kind only.

Every mode also fixes torch's intra-op thread count (``threads``, 1 unless a run's ``threads=`` says
otherwise): how many threads share a reduction or a product can change its rounding, so tools
(``score.py``, ``evaluate.py``, the leaderboard, the analyses) evaluate on the thread count ``train.py``
trained and evaluated on, whatever the machine's cores. ``speed/evaluation_speed.py`` times a saved
policy's step on one thread and on torch's default of one per core.

Both variables are read when torch and MKL load, so ``apply`` must run before ``import torch``;
after it, ``apply`` only checks that the process already runs the mode's torch settings (``fma``
and ``portable`` share them, so a process can switch between those two) and says how to fix it
if not. ``in_effect()`` reads what the process actually runs (torch's kernel set, MKL's branch)
for ``summary.json``. This module imports nothing heavy.
"""

from __future__ import annotations

import os
import sys
import warnings

MODES = ("fma", "portable", "native")
DEFAULT = "fma"
PORTABLE_KERNELS = "AVX2"  # torch.backends.cpu.get_cpu_capability() under ATEN_CPU_CAPABILITY=avx2
PORTABLE_ENV = {"ATEN_CPU_CAPABILITY": "avx2", "MKL_CBWR": "COMPATIBLE"}

# mkl_cbwr_get's branch codes (mkl_service.h), for in_effect()
_MKL_BRANCHES = {0: "OFF", 1: "BRANCH_OFF", 2: "AUTO", 3: "COMPATIBLE", 4: "SSE2", 6: "SSSE3", 7: "SSE4_1",
                 8: "SSE4_2", 9: "AVX", 10: "AVX2", 11: "AVX512_MIC", 12: "AVX512", 13: "AVX512_MIC_E1",
                 14: "AVX512_E1"}


class NumericsError(RuntimeError):
    """The process cannot run the requested numerics mode (torch loaded under another)."""


THREADS = 1  # torch's intra-op threads unless a run asks for more (conf/config.yaml's threads)
_applied: str | None = None  # the mode last applied in this process (None: apply never ran)


def apply(mode: str, threads: int = THREADS) -> None:
    """Make this process run ``mode`` on ``threads`` intra-op threads: set its variables if torch has
    not loaded yet, or check that the loaded torch already runs it (``NumericsError`` with the remedy
    if not) and set its thread count; then switch the stacked layers' products to the project's
    kernels (``fma``) or to torch's."""
    global _applied
    if mode not in MODES:
        raise ValueError(f"numerics must be one of {MODES}, got {mode!r}")
    from learners import kernels

    try:
        kernels.isa_cap()  # a bad $RACING_KERNEL_ISA is refused before anything is written
    except kernels.KernelError as err:
        raise NumericsError(str(err)) from None
    if "torch" not in sys.modules:
        for key, value in PORTABLE_ENV.items():
            if mode in ("fma", "portable"):
                os.environ[key] = value
            else:
                os.environ.pop(key, None)
        os.environ["OMP_NUM_THREADS"] = str(threads)  # torch's default thread count when it loads
        _warn_if_unportable(mode)
    else:
        current = _torch_mode()
        if current != ("native" if mode == "native" else "portable"):
            raise NumericsError(
                f"numerics={mode} was asked for, but this process loaded torch with {current} numerics "
                f"(kernels {_torch_kernels()}, MKL branch {mkl_branch()}); they are fixed when torch "
                f"loads. Start a new process, or set "
                + ("no " + " or ".join(PORTABLE_ENV) if mode == "native"
                   else " ".join(f"{k}={v}" for k, v in PORTABLE_ENV.items()))
                + " in its environment before torch is imported")
        sys.modules["torch"].set_num_threads(threads)
    _use_products(mode)
    _applied = mode


def applied() -> str | None:
    """The mode ``apply`` last set in this process; None if it never ran (torch then runs whatever it
    loaded with, on its default thread count)."""
    return _applied


_fallback: str | None = None  # why numerics=fma, as last applied, runs portable instead (warned once)


def _use_products(mode: str) -> None:
    global _fallback
    from learners import kernels

    reason = kernels.use(mode == "fma")
    if reason is not None and reason != _fallback:
        warnings.warn(f"numerics=fma: the project's matrix kernels cannot run here ({reason}); running "
                      "numerics=portable instead (summary.json records it)", RuntimeWarning, stacklevel=3)
    _fallback = reason


def _portable_kernels_available() -> bool:
    """Whether this CPU runs torch's AVX2 kernels (x86-64 with AVX2 and FMA)."""
    import platform

    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    from door import files

    try:
        text = files.read_text("/proc/cpuinfo", 1 << 24, "system file", follow=True)
        flags = next((line for line in text.splitlines() if line.startswith("flags")), "").split()
        return "avx2" in flags and "fma" in flags
    except (OSError, ValueError):
        return True  # not Linux: torch says after loading (in_effect)


def _warn_if_unportable(mode: str) -> None:
    if mode in ("fma", "portable") and not _portable_kernels_available():
        warnings.warn(f"numerics={mode}: this CPU cannot run the AVX2 kernels it relies on; results here are "
                      "this machine's own (summary.json records the kernels that ran)", RuntimeWarning,
                      stacklevel=3)


def mkl_branch() -> str | None:
    """MKL's conditional-numerical-reproducibility branch in this process (``None`` if MKL's
    query function cannot be found: a torch without MKL, or another platform)."""
    import ctypes

    import torch

    path = os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so")
    try:
        get = ctypes.CDLL(path).mkl_serv_cbwr_get
    except (OSError, AttributeError):
        return None
    get.restype, get.argtypes = ctypes.c_int, [ctypes.c_int]
    code = get(-1)  # MKL_CBWR_ALL: the branch and the STRICT flag
    name = _MKL_BRANCHES.get(code & 0xFFFF, str(code & 0xFFFF))
    return name + (",STRICT" if code & 0x10000 else "")


def _torch_kernels() -> str:
    import torch

    return torch.backends.cpu.get_cpu_capability()


def _torch_mode() -> str:
    """``portable`` when torch runs its AVX2 kernels and MKL the COMPATIBLE branch (or has no
    such switch), else ``native``."""
    portable = (os.environ.get("ATEN_CPU_CAPABILITY") == PORTABLE_ENV["ATEN_CPU_CAPABILITY"]
                and mkl_branch() in (PORTABLE_ENV["MKL_CBWR"], None))
    return "portable" if portable else "native"


def in_effect() -> dict:
    """What this process runs: ``{"mode", "kernels", "mkl_branch", "products"}``. ``mode`` is
    ``fma`` when torch runs portably and the stacked layers' products are the project's,
    ``portable`` when they are MKL's COMPATIBLE ones, else ``native``; ``products`` names the
    products' code (``fma-avx512``, ``fma-avx2``, ``fma-scalar``: the same bits; or ``torch``),
    and ``fallback`` says why ``fma`` was asked for and not run, where that happened."""
    from learners import kernels

    mode = _torch_mode()
    if mode == "portable" and kernels.active():
        mode = "fma"
    effect = {"mode": mode, "kernels": _torch_kernels(), "mkl_branch": mkl_branch(),
              "products": f"fma-{kernels.best_isa()}" if kernels.active() else "torch"}
    if _fallback is not None:
        effect["fallback"] = _fallback
    return effect
