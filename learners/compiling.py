"""Compiled update steps (``compile=true``): each step's loss, forward and backward, through
``torch.compile`` (TorchInductor's C++ backend on the CPU).

What is compiled: the function from a minibatch to the step's objective (the loss module's
forward pass and the sum of its terms); its backward pass is compiled with it (AOTAutograd).
Drawing the minibatch and the optimiser's step stay eager: they use the members' generators and
a step counter that would recompile the graph every step.

Numerics: the matrix products stay ATen's (MKL's, as in eager mode); inductor generates and
fuses the element-wise work, which rounds differently from eager kernels, so a compiled run is
not an eager run to the bit (``summary.json`` says which ran, and ``report.py`` refuses to mix
them). Generated kernels are pinned to AVX2 (``simdlen=256``) in both numerics modes: in
portable mode so that every AVX2 or AVX-512 CPU runs the same code, and in native mode because
the AVX-512 kernels inductor generated for these networks corrupted the heap with torch 2.13 and
gcc 12 (seen on an AVX-512 Xeon). Portable mode also compiles for ``-march=x86-64-v3`` (the AVX2
level) instead of ``-march=native``. No loss draws random numbers inside a compiled step (the
members' draws are made ahead, eagerly); should one, ``fallback_random`` keeps ATen's generators,
as eager mode does.

Inductor's cache (generated C++ and Python it loads and runs) is kept in a folder of this user's
own, ``<the kernel cache's parent>/inductor`` (``inductor_cache``: made with mode 0700, owned by
this user, not a link, never one under a shared ``/tmp`` another user could have made first),
unless ``$TORCHINDUCTOR_CACHE_DIR`` names one; ``summary.json``'s ``compile`` record names it.
Like the project's own source, what is in it is trusted as this user's files.
"""

from __future__ import annotations

import os
import platform
import shutil
import sys
import warnings
from collections.abc import Callable

import torch


def unavailable_reason(device: str = "cpu") -> str | None:
    """Why update steps cannot be compiled here (one line), or None if they can."""
    if not str(device).startswith("cpu"):
        return None  # CUDA compiles through Triton, which torch brings along
    if not sys.platform.startswith("linux"):
        return f"compiling on the CPU is supported on Linux only (this is {sys.platform})"
    if platform.machine() not in ("x86_64", "AMD64"):
        return f"compiling on the CPU is set up for x86-64 only (this is {platform.machine()})"
    from torch._inductor import config

    compiler = config.cpp.cxx[-1] if isinstance(config.cpp.cxx, tuple) else config.cpp.cxx
    if not compiler or shutil.which(compiler) is None:
        return (f"no C++ compiler {compiler!r} found (TorchInductor builds its CPU kernels with one; "
                "install g++ or set CXX)")
    return None


def inductor_cache() -> str:
    """The folder TorchInductor caches its generated code in (set for this process): the user's
    ``$TORCHINDUCTOR_CACHE_DIR``, or ``inductor`` beside the project's kernel cache, made private
    (mode 0700), checked to be this user's and not a link. ``RuntimeError`` saying why otherwise.
    The variable at torch's own default (``<tmp>/torchinductor_<user>``) is no choice of the user's:
    ``import torch._inductor.config`` sets it so itself, a folder under the shared temporary one."""
    from torch._inductor.runtime.cache_dir_utils import default_cache_dir

    from learners.kernels import cache_dir
    from door import files

    chosen = os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    if chosen and os.path.abspath(chosen) != os.path.abspath(default_cache_dir()):
        return chosen
    folder = cache_dir().parent / "inductor"
    try:
        files.private(folder)  # only this user may plant code in it
    except (OSError, files.FileRefused) as err:
        raise RuntimeError(f"the compile cache {folder} cannot be used: {err}") from None
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(folder)
    return str(folder)


def configure(numerics: str) -> None:
    """Set TorchInductor up for this process's numerics mode (see the module docstring), from a
    clean slate: what a run compiles must not depend on what the process compiled before it
    (graphs compiled for other shapes or objects would be reused, recompiled with dynamic
    shapes, or past the cache limit replaced by eager code, each rounding differently)."""
    from torch._inductor import config

    torch._dynamo.reset()
    config.cpp.simdlen = 256
    config.cpp.march = "x86-64-v3" if numerics == "portable" else None
    config.fallback_random = True
    _quiet()


def _quiet() -> None:
    """TensorDict's notes on tracing (a deprecated dynamo flag it sets, locks it cannot enforce in a
    graph) say nothing about a run; they would be printed on every compiled step's first call.
    (Set per run: the filters may have been reset since, as pytest does per test.)"""
    warnings.filterwarnings("ignore", message=r"Using lock_\(\) inside a compiled graph", category=UserWarning)
    warnings.filterwarnings("ignore", message=r"torch._dynamo.config.inline_inbuilt_nn_modules is deprecated",
                            category=FutureWarning)


def compile_step(fn: Callable, enabled: bool) -> Callable:
    """``fn`` compiled (or ``fn`` itself when not ``enabled``)."""
    return torch.compile(fn, dynamic=False) if enabled else fn


def seconds_spent() -> float:
    """Seconds this process has spent compiling so far (graphs and their backward passes)."""
    from torch._dynamo.utils import calculate_time_spent

    return float(calculate_time_spent().get("total_wall_time", 0.0))
