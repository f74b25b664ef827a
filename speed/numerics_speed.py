"""What each numerics mode costs (``engine/numerics.py``), measured in this run: training time
per cell, and the matrix products alone per shape against the core's FMA peak.

    python -m speed.numerics_speed [--episodes 20] [--members 1 5 25] [--repeats 3]
                                        [--cells spg_p_multi/hybrid ppo/recent sac/memory]
                                        [--modes fma portable native] [--no-cells] [--no-shapes]

A mode is fixed when torch loads, so each measurement is a child process (this script with
``--child`` or ``--child-shapes``); the modes alternate, ``--repeats`` times, and each table
keeps every mode's fastest repeat (the machine's noise only ever adds time).

1. Training per member-episode (ms, collection and training, start-up excluded; one thread, as
   training runs use), per cell and population size R, with the ratios fma / native (what the
   exact default costs against this CPU's fastest) and portable / fma (what the project's
   products save against MKL's COMPATIBLE branch).
2. The stacked layers' products at the networks' shapes (forward, input gradient, weight
   gradient), GFLOP/s and % of the core's FMA peak: MKL native, MKL COMPATIBLE (portable), and
   the project's kernels on their AVX2 and widest paths. The peak is measured here: rounds of 24
   independent vector FMAs on registers (``learners.kernels.peak_gflops``), 2 flops per lane.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from engine.budget import EPISODES, count
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CELLS = ["spg_p_multi/hybrid", "ppo/recent", "sac/memory"]
MODES = ["fma", "portable", "native"]
TRACKS = [2067791, 5468063, 5412436, 8273186, 773203]
# (name, rows, in, out): the layers the networks run (critic 8 -> 100 -> 100 -> 1, actor 6 -> 100 -> 2 heads)
SHAPES = [("hidden 100x100, minibatch 200", 200, 100, 100), ("input 8 -> 100, minibatch 200", 200, 8, 100),
          ("output 100 -> 1, minibatch 200", 200, 100, 1), ("SPG scoring 100x100, 1400 pairs", 1400, 100, 100),
          ("SAC hidden 100x100, minibatch 256", 256, 100, 100)]


def child(mode: str, cell: str, members: int, episodes: int) -> None:
    """Train one population in this process under ``mode``; print its timed phases as JSON."""
    from engine import numerics

    numerics.apply(mode)
    from engine.config import RunConfig
    from engine.runner import train_population

    algo, er = cell.split("/")
    seeds = [*TRACKS, *range(1000, 1000 + max(0, members - len(TRACKS)))][:members]
    settings = [f"algo={algo}", f"er={er}", f"seeds=[{','.join(map(str, seeds))}]", f"episodes={episodes}",
                "progress=false", "logger=none", "checkpoint_every=0", f"numerics={mode}"]
    cfg = RunConfig.compose(*settings)
    if cfg.algo.td is not None:  # an off-policy learner: one warm-up episode, then gradient steps
        cfg = RunConfig.compose(*settings, "algo.td.warmup_episodes=1")
    with tempfile.TemporaryDirectory() as out:
        summary = train_population(cfg, Path(out))[0]
    print(json.dumps({"seconds": summary["time/rollout_s"] + summary["time/train_s"],
                      "numerics": summary["numerics"]}))


def child_shapes(mode: str, members: list[int]) -> None:
    """Time the products at SHAPES under ``mode`` (MKL's under portable and native, the project's
    kernels on each path under fma); print {label: seconds} as JSON."""
    from engine import numerics

    numerics.apply(mode)
    import torch

    from learners import kernels
    from learners.kernels import ops

    from speed.train_speed import best_of

    paths = [p for p in ("avx2", "avx512") if p in kernels.isas()] if mode == "fma" else ["mkl"]
    result = {}
    for name, rows, n_in, n_out in SHAPES:
        for r in members:
            g = torch.Generator().manual_seed(0)
            x = torch.randn(r, rows, n_in, generator=g)
            w = torch.randn(r, n_out, n_in, generator=g)
            b = torch.randn(r, n_out, generator=g)
            dy = torch.randn(r, rows, n_out, generator=g)
            for path in paths:
                if path == "mkl":
                    fns = {"forward": lambda: torch.baddbmm(b.unsqueeze(1), x, w.transpose(1, 2)),
                           "input grad": lambda: torch.bmm(dy, w),
                           "weight grad": lambda: torch.bmm(dy.transpose(1, 2), x)}
                else:
                    fns = {"forward": lambda p=path: ops.bmm(x, w.transpose(1, 2), b, isa=p),
                           "input grad": lambda p=path: ops.bmm(dy, w, isa=p),
                           "weight grad": lambda p=path: ops.bmm(dy.transpose(1, 2), x, isa=p)}
                for op, fn in fns.items():
                    fn()  # warm-up (the kernels' workspace, the allocator)
                    result[json.dumps([name, r, op, path])] = best_of(fn, 20)
    if mode == "fma":
        result["peak"] = {p: kernels.peak_gflops(p) for p in paths}
    print(json.dumps(result))


def _run_child(args: list[str]) -> dict:
    env = {**os.environ, "RL_LOGGING_LEVEL": "WARNING", "PYTHONWARNINGS": "ignore"}
    result = subprocess.run([sys.executable, "-m", "speed.numerics_speed", *args], cwd=ROOT, env=env,
                            capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed:\n{result.stderr[-2000:]}")
    return json.loads(result.stdout.splitlines()[-1])


def cell_table(args) -> None:
    from speed.train_speed import table

    rows, kernels = [], {}
    for cell in args.cells:
        for members in args.members:
            best = {mode: float("inf") for mode in args.modes}
            for _ in range(args.repeats):
                for mode in args.modes:
                    result = _run_child(["--child", mode, cell, str(members), str(args.episodes)])
                    best[mode] = min(best[mode], result["seconds"])
                    kernels[mode] = result["numerics"]
            per = 1000 / (members * args.episodes)
            row = [cell, members, *(f"{best[m] * per:.1f}" for m in args.modes)]
            if "fma" in best and "native" in best:
                row.append(f"{best['fma'] / best['native']:.2f}x")
            if "fma" in best and "portable" in best:
                row.append(f"{best['portable'] / best['fma']:.2f}x")
            rows.append(row)
    header = ["cell", "R", *args.modes]
    if "fma" in args.modes and "native" in args.modes:
        header.append("fma / native")
    if "fma" in args.modes and "portable" in args.modes:
        header.append("portable / fma")
    print(f"{args.episodes} episodes per run, one thread, best of {args.repeats} alternated repeats; "
          + "; ".join(f"{mode}: {k['kernels']} kernels, MKL {k['mkl_branch']}, products {k.get('products', 'torch')}"
                      for mode, k in kernels.items()))
    table("Training per member-episode (ms, collection and training)", header, rows)


def shape_table(args) -> None:
    from speed.train_speed import table

    modes = [m for m in ("native", "portable", "fma") if m in args.modes]
    best: dict[str, float] = {}
    peak: dict[str, float] = {}
    for _ in range(args.repeats):
        for mode in modes:
            result = _run_child(["--child-shapes", mode, *map(str, args.members)])
            for key, value in result.pop("peak", {}).items():
                peak[key] = max(peak.get(key, 0.0), value)
            for key, value in result.items():
                label = json.dumps([*json.loads(key)[:3], mode if mode != "fma" else "fma-" + json.loads(key)[3]])
                best[label] = min(best.get(label, float("inf")), value)
    columns = [c for c in ("native", "portable", "fma-avx2", "fma-avx512")
               if any(json.loads(k)[3] == c for k in best)]
    top = max(peak.values()) if peak else None
    rows = []
    for name, n_rows, n_in, n_out in SHAPES:
        for r in args.members:
            for op in ("forward", "input grad", "weight grad"):
                flops = 2 * r * n_rows * n_in * n_out
                cells = []
                for c in columns:
                    t = best.get(json.dumps([name, r, op, c]))
                    gf = flops / t / 1e9 if t else None
                    cells.append("" if gf is None else f"{gf:.0f}" + (f" ({100 * gf / top:.0f}%)" if top else ""))
                rows.append([name, r, op, *cells])
    print("\nFMA peak of one core (GFLOP/s, measured): "
          + ", ".join(f"{k} {v:.0f}" for k, v in sorted(peak.items())) + "; percentages are of the widest")
    table("Products of the stacked layers (GFLOP/s, % of the FMA peak; one thread)",
          ["layer", "R", "product", *columns], rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=EPISODES, default=20)
    parser.add_argument("--members", type=count(1, 1000), nargs="+", default=[1, 5, 25])
    parser.add_argument("--cells", nargs="+", default=CELLS)
    parser.add_argument("--modes", nargs="+", default=MODES, choices=MODES)
    parser.add_argument("--repeats", type=count(1, 1000), default=3)
    parser.add_argument("--no-cells", action="store_true", help="skip the training table")
    parser.add_argument("--no-shapes", action="store_true", help="skip the products table")
    parser.add_argument("--child", nargs=4, metavar=("MODE", "CELL", "MEMBERS", "EPISODES"), help=argparse.SUPPRESS)
    parser.add_argument("--child-shapes", nargs="+", metavar="MODE_THEN_MEMBERS", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        mode, cell, members, episodes = args.child
        child(mode, cell, int(members), int(episodes))
        return 0
    if args.child_shapes:
        child_shapes(args.child_shapes[0], [int(m) for m in args.child_shapes[1:]])
        return 0
    if not args.no_shapes:
        shape_table(args)
    if not args.no_cells:
        cell_table(args)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.numerics_speed", main))
