"""The project's own float32 matrix products: every output element one fixed chain of FMAs.

``c[i, j]`` starts from zero and takes ``acc = fma(a[i, k], b[k, j], acc)`` for k = 0, 1, ...,
K - 1 in that order (one rounding per step), then adds the bias once. FMA is exactly rounded
by IEEE 754, so the bits are the same on every CPU, whatever its vector width: the AVX-512,
AVX2 and portable scalar paths of ``gemm.cpp`` agree to the bit, and a population member's
product never depends on the other members in the call. torch's and MKL's products split
and reorder the sum by CPU, which is why ``numerics=portable`` has to run MKL's slow
COMPATIBLE branch; ``numerics=fma`` (``engine/numerics.py``) runs these instead.

The library is compiled from ``gemm.cpp`` on first use with the system's C++ compiler (``$CXX``,
else ``g++``, ``c++`` or ``clang++``), about two seconds, and cached per source, compiler and
architecture in ``$RACING_KERNEL_CACHE`` (default ``~/.cache/racing-rl/kernels``). Where no
compiler works, ``unavailable_reason()`` says why and the caller falls back to torch's products.

This module is torch-free (``engine.numerics`` switches the products on before torch loads);
``learners.kernels.ops`` holds the torch side: ``bmm``, ``colsum`` and ``linear``, the stacked
layer's forward and backward that ``learners.networks.StackedLinear`` runs while ``active()``.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import platform
import shutil
import subprocess
import warnings
from pathlib import Path

from door import files


SOURCE = Path(__file__).with_name("gemm.cpp")
FLAGS = ["-O3", "-std=c++17", "-shared", "-fPIC", "-ffp-contract=off"]
ISAS = {"scalar": 0, "avx2": 1, "avx512": 2}  # gemm.cpp's instruction-set codes


class KernelError(RuntimeError):
    """The kernels cannot be built or loaded here (the message says why)."""


def cache_dir() -> Path:
    env = os.environ.get("RACING_KERNEL_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "racing-rl" / "kernels"


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), "g++", "c++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _build() -> tuple[Path, str]:
    """The compiled library's path and SHA-256, compiling it first if this source and compiler have
    none yet, or if the cached one is not the file that was built (its digest, recorded beside it when
    it was built, does not match: a damaged or altered library is rebuilt, never loaded, and a
    warning says so)."""
    cxx = _compiler()
    if cxx is None:
        raise KernelError("no C++ compiler found (set CXX, or install g++)")
    try:
        version = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError) as err:
        raise KernelError(f"the C++ compiler {cxx} does not run: {err}") from None
    source = files.read(SOURCE, 1 << 22, "kernel source")
    key = hashlib.sha256(b"\0".join([source, " ".join(FLAGS).encode(), version.encode(),
                                     platform.machine().encode()])).hexdigest()[:16]
    folder = cache_dir()
    try:  # a folder whose library is loaded as code: this user's alone (not a link, mode 0700)
        files.private(folder)
    except (OSError, files.FileRefused) as err:
        raise KernelError(f"the kernel cache {folder} cannot be used: {err} (set RACING_KERNEL_CACHE)") from None
    path = folder / f"gemm-{key}.so"
    record = folder / f"gemm-{key}.so.sha256"
    if os.path.lexists(path):
        try:
            recorded = files.read_text(record, 200, "kernel digest").strip()
            owners = {os.lstat(path).st_uid, os.lstat(record).st_uid}
            if hasattr(os, "getuid") and owners != {os.getuid()}:
                problem = f"or its record belongs to another user (uid {sorted(owners)})"
            elif files.digest(path)["sha256"] == recorded:
                return path, recorded
            else:
                problem = "differs from the library that was built (its SHA-256 does not match the one recorded)"
        except FileNotFoundError:
            problem = "has no record of its SHA-256 (built by an earlier version, or its record was lost)"
        except (OSError, files.FileRefused) as err:
            problem = f"cannot be checked ({err})"
        warnings.warn(f"the cached kernel library {path} {problem}; it is rebuilt, not loaded", RuntimeWarning,
                      stacklevel=4)
    try:
        with files.build(path) as tmp:
            result = subprocess.run([cxx, *FLAGS, str(SOURCE), "-o", str(tmp)], capture_output=True, text=True,
                                    timeout=300)
            if result.returncode != 0:
                raise KernelError(f"{cxx} failed to compile {SOURCE.name}: {result.stderr.strip()[-2000:]}")
            sha256 = files.digest(tmp)["sha256"]
            files.write_text(record, sha256 + "\n")  # before the library: a library is never without its record
    except (OSError, subprocess.SubprocessError, files.FileRefused) as err:
        raise KernelError(f"compiling {SOURCE.name} with {cxx} into the kernel cache {folder} failed: {err} "
                          "(set RACING_KERNEL_CACHE to a folder this user can write)") from None
    return path, sha256


@functools.lru_cache(maxsize=None)
def _load() -> tuple[ctypes.CDLL | None, str | None]:
    try:
        lib = files.load_library(*_build())  # the very bytes whose digest was checked
    except KernelError as err:
        return None, str(err)
    except (OSError, files.FileRefused) as err:
        return None, f"the compiled kernels do not load: {err}"
    try:
        i64, ptr = ctypes.c_int64, ctypes.c_void_p
        lib.racing_gemm_isas.restype, lib.racing_gemm_isas.argtypes = ctypes.c_int, []
        lib.racing_gemm.restype = ctypes.c_int
        lib.racing_gemm.argtypes = [ctypes.c_int, i64, i64, i64, i64, ptr, i64, i64, i64, ptr, i64, i64, i64,
                                    ptr, i64, i64, i64, ptr, i64, i64]
        lib.racing_colsum.restype = None
        lib.racing_colsum.argtypes = [i64, i64, i64, ptr, i64, i64, i64, ptr, i64]
        lib.racing_fma_loop.restype, lib.racing_fma_loop.argtypes = ctypes.c_float, [ctypes.c_int, i64]
        lib.racing_sqrt.restype, lib.racing_sqrt.argtypes = ctypes.c_int, [ctypes.c_int, i64, ptr, ptr]
    except AttributeError as err:  # a library without the kernels' functions: not the one built from gemm.cpp
        return None, f"the compiled kernels do not load: the cached library lacks {err}"
    return lib, None


def unavailable_reason() -> str | None:
    """Why the kernels cannot run in this process (one line), or None if they can."""
    return _load()[1]


def _lib() -> ctypes.CDLL:
    lib, reason = _load()
    if lib is None:
        raise KernelError(reason)
    return lib


def isas() -> list[str]:
    """The instruction-set paths this CPU can run, narrowest first (``scalar`` always)."""
    mask = _lib().racing_gemm_isas()
    return [name for name, code in ISAS.items() if mask >> code & 1]


@functools.lru_cache(maxsize=None)
def best_isa() -> str:
    """The path ``bmm`` and ``linear`` use unless told otherwise: the widest this CPU runs, or
    at most ``$RACING_KERNEL_ISA`` (``scalar``, ``avx2`` or ``avx512``; tests use it to take the
    wider instruction sets away, as an older CPU would). Read once per process."""
    available = isas()
    cap = isa_cap()
    if cap:
        available = [isa for isa in available if ISAS[isa] <= ISAS[cap]]
    return available[-1]


def isa_cap() -> str | None:
    """``$RACING_KERNEL_ISA`` (None where unset); ``KernelError`` if it names no instruction set
    (``engine.numerics.apply`` checks it before a run writes anything)."""
    cap = os.environ.get("RACING_KERNEL_ISA")
    if cap and cap not in ISAS:
        raise KernelError(f"the environment variable RACING_KERNEL_ISA must be one of {sorted(ISAS)} (or unset), "
                          f"got {cap!r}")
    return cap or None


LANES = {"scalar": 1, "avx2": 8, "avx512": 16}


def peak_gflops(isa: str | None = None, seconds: float = 0.2) -> float:
    """The core's float32 FMA peak on a vector path (default: the widest), in GFLOP/s, measured:
    rounds of 24 independent vector FMAs (``racing_fma_loop``), two flops per lane, timed over
    about ``seconds``, best of three (the machine's noise only ever adds time)."""
    import time

    isa = isa or best_isa()
    if isa not in ("avx2", "avx512") or isa not in isas():
        raise KernelError(f"no FMA peak for the {isa} path on this CPU (it runs {isas()})")
    lib, code = _lib(), ISAS[isa]
    rounds = 1000
    while True:  # size the loop to about `seconds`
        start = time.perf_counter()
        lib.racing_fma_loop(code, rounds)
        elapsed = time.perf_counter() - start
        if elapsed > seconds / 10:
            break
        rounds *= 4
    rounds = int(rounds * seconds / elapsed)
    best = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        lib.racing_fma_loop(code, rounds)
        best = min(best, time.perf_counter() - start)
    return rounds * 24 * LANES[isa] * 2 / best / 1e9


def _isa_code(isa: str | None) -> int:
    if isa is None:
        return ISAS[best_isa()]
    if isa not in ISAS:
        raise ValueError(f"isa must be one of {sorted(ISAS)}, got {isa!r}")
    if isa not in isas():
        raise KernelError(f"this CPU cannot run the {isa} path (it runs {isas()})")
    return ISAS[isa]


_ACTIVE = False


def use(on: bool) -> str | None:
    """Switch the stacked layers' products to these kernels (``on``) or to torch's. Returns
    None, or why the kernels cannot run here (then torch's products stay in use)."""
    global _ACTIVE
    reason = unavailable_reason() if on else None
    _ACTIVE = bool(on) and reason is None
    return reason


def active() -> bool:
    """Whether the stacked layers compute their products with these kernels (``use``)."""
    return _ACTIVE
