"""Population training speed: solo runs against populations, and training against the matmul peak.

    python -m speed.population_speed [--episodes 20] [--sizes 1 5 25 100]
                                          [--cells ppo/recent spg_p_multi/hybrid spg/memory]
                                          [--modes eager compiled] [--numerics portable|native]
                                          [--before COMMIT] [--collectors 25] [--processes 2]

Prints three tables (one thread, as training runs use; absolute numbers depend on the machine,
compare the ratios, all measured in this run):

1. per cell, population size R and mode (eager, or ``compile=true``): wall time (compiling
   included), the seconds spent compiling, time per member-episode split into collection and
   training (compiling excluded, so the steady rate), throughput per core against an eager solo
   run (R = 1, the same code; compiling included), training's achieved GFLOP/s (matmul FLOPs
   counted with ``torch.utils.flop_counter`` on a population of one, forward and backward,
   padding rows included) beside this core's matmul peak (a 1024 x 1024 float32 matmul in the
   same numerics, measured again right before each row; the header also gives ``bmm`` at a
   training layer's shape);
2. collection per member-step with the direct loop and with TorchRL's ``Collector`` at the
   sizes given by ``--collectors``;
3. with ``--before COMMIT``: the same solo runs with that commit's code (a clean export, run
   as a subprocess of this script), the baseline of "today's solo run";
4. with ``--processes N``: the largest population of each cell (first mode) split over N
   processes (``processes=N``: the same results), wall time against one process, process
   start-up included.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")

from engine.budget import EPISODES, PROCESSES, count as whole
from engine import numerics  # noqa: E402

# Before torch loads (engine/numerics.py); --numerics is read here, before the argument parser.
MODE = sys.argv[sys.argv.index("--numerics") + 1] if "--numerics" in sys.argv[:-1] else numerics.DEFAULT
numerics.apply(MODE)

import torch  # noqa: E402
from torch.utils._python_dispatch import TorchDispatchMode  # noqa: E402
from torch.utils.flop_counter import flop_registry  # noqa: E402

from engine.config import RunConfig  # noqa: E402
from speed.train_speed import best_of, table  # noqa: E402
from engine.outputs import read_summary  # noqa: E402
from engine.runner import train_population  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
CELLS = ["ppo/recent", "spg_p_multi/hybrid", "spg/memory"]
SEEDS = RunConfig.compose("+experiment=wide_grid").seeds  # fixed tracks; more are derived if needed


def member_seeds(count: int) -> list[int]:
    return [*SEEDS, *range(1000, 1000 + max(0, count - len(SEEDS)))][:count]


def config(cell: str, members: int, episodes: int, *extra: str) -> RunConfig:
    algo, er = cell.split("/")
    seeds = ",".join(map(str, member_seeds(members)))
    return RunConfig.compose(f"algo={algo}", f"er={er}", f"episodes={episodes}", "progress=false", f"numerics={MODE}",
                             "logger=none", "checkpoint_every=0", f"seeds=[{seeds}]", *extra)


def timed_run(cfg: RunConfig) -> dict:
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        summary = train_population(cfg, Path(out))[0]
        wall = time.perf_counter() - start
    compiling = summary.get("time/compile_s", 0.0)
    return {"wall": wall, "rollout": summary["time/rollout_s"], "train": summary["time/train_s"] - compiling,
            "compile": compiling}


class _FlopCount(TorchDispatchMode):
    """``FlopCounterMode``'s per-operator counts (``flop_registry``) without its module tracker,
    which cannot walk TorchRL's TensorDict-held parameters (SAC, TD3)."""

    def __init__(self):
        super().__init__()
        self.total = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        count = flop_registry.get(func._overloadpacket)
        if count is not None:
            self.total += count(*args, **kwargs, out_val=out)
        return out


def counted_flops(cell: str, episodes: int) -> float:
    """Matmul FLOPs of one member's run (every member's are the same)."""
    counter = _FlopCount()
    with counter, tempfile.TemporaryDirectory() as out:
        train_population(config(cell, 1, episodes), Path(out))
    return float(counter.total)


def square_matmul_peak(calls: int = 5, repeats: int = 3) -> float:
    """GFLOP/s of a 1024^2 float32 matmul now (measured again before every row: a shared machine's
    speed drifts within a benchmark run, by 2x over an hour here)."""
    a, b = torch.randn(1024, 1024), torch.randn(1024, 1024)
    return 2 * 1024 ** 3 / best_of(lambda: [a @ b for _ in range(calls)], repeats) * calls / 1e9


def matmul_peaks() -> dict[str, float]:
    """GFLOP/s of a 1024^2 matmul and of bmm at a 25-member 200 x 100 x 100 layer."""
    x, w = torch.randn(25, 200, 100), torch.randn(25, 100, 100)
    batched = 2 * 25 * 200 * 100 * 100 / best_of(lambda: [torch.bmm(x, w) for _ in range(50)], 5) * 50
    return {"matmul 1024^2": square_matmul_peak(10, 5), "bmm 25x200x100x100": batched / 1e9}


def before_solo(commit: str, cell: str, episodes: int) -> dict:
    """A solo run of ``cell`` with ``commit``'s code (exported with clean_sweep's export)."""
    from clean_sweep import export, resolve_commit

    sha = resolve_commit(commit)
    code = export(sha, ROOT / "outputs" / "code" / sha[:12])
    algo, er = cell.split("/")
    with tempfile.TemporaryDirectory() as out:
        cmd = [sys.executable, "train.py", f"algo={algo}", f"er={er}", f"seed={member_seeds(1)[0]}",
               f"episodes={episodes}", "progress=false", "logger=none", "checkpoint_every=0",
               f"hydra.run.dir={out}"]
        start = time.perf_counter()
        subprocess.run(cmd, cwd=code, check=True, capture_output=True,
                       env={**os.environ, "PYTHONPATH": str(code)})
        wall = time.perf_counter() - start
        summary = read_summary(Path(out))
    return {"wall": wall, "rollout": summary["time/rollout_s"], "train": summary["time/train_s"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=EPISODES, default=20)
    parser.add_argument("--sizes", type=whole(1, 1000), nargs="+", default=[1, 5, 25, 100])
    parser.add_argument("--cells", nargs="+", default=CELLS)
    parser.add_argument("--numerics", choices=numerics.MODES, default=numerics.DEFAULT,
                        help="the numerics of every run and of the matmul peak (engine/numerics.py)")
    parser.add_argument("--modes", nargs="+", default=["eager"], choices=["eager", "compiled"],
                        help="eager and/or compiled update steps (compile=true)")
    parser.add_argument("--collectors", type=whole(1, 1000), nargs="*", default=[25],
                        help="population sizes at which to compare the two collectors")
    parser.add_argument("--before", default=None, help="a commit whose solo runs are the baseline")
    parser.add_argument("--processes", type=PROCESSES, nargs="*", default=[],
                        help="also train the largest population split over this many processes")
    args = parser.parse_args(argv)
    if 1 not in args.sizes:
        parser.error("--sizes must include 1 (the solo baseline)")
    peaks = matmul_peaks()
    print(f"episodes per run: {args.episodes}; numerics {MODE}; torch {torch.__version__}, one thread; matmul peak here: "
          + ", ".join(f"{k} {v:.1f} GFLOP/s" for k, v in peaks.items()))

    rows, solo, timed = [], {}, {}
    for cell in args.cells:
        flops = counted_flops(cell, args.episodes)
        for size in args.sizes:
            for mode in args.modes:
                peak = square_matmul_peak()
                t = timed[cell, size, mode] = timed_run(config(cell, size, args.episodes,
                                                               f"compile={mode == 'compiled'}"))
                per = size * args.episodes
                if size == 1 and mode == args.modes[0]:
                    solo[cell] = t
                gflops = flops * size / t["train"] / 1e9
                rows.append([cell, size, mode, f"{t['wall']:.1f}", f"{t['compile']:.1f}",
                             f"{1000 * t['wall'] / per:.1f}", f"{1000 * t['rollout'] / per:.1f}",
                             f"{1000 * t['train'] / per:.1f}", f"{solo[cell]['wall'] / (t['wall'] / size):.2f}x",
                             f"{gflops:.1f}", f"{peak:.1f}", f"{gflops / peak:.0%}"])
    table(f"Populations against a solo run (same code, {args.modes[0]}); per member-episode times; wall includes "
          "compiling, train ms excludes it",
          ["cell", "R", "mode", "wall s", "compile s", "ms/member-ep", "collect ms", "train ms",
           "throughput vs solo", "train GFLOP/s", "peak GFLOP/s (before the row)", "of matmul peak"], rows)

    rows = []
    for size in args.collectors:
        for cell in args.cells[:1]:
            times = {}
            for backend in ("direct", "torchrl"):
                t = timed_run(config(cell, size, args.episodes, f"env.collector={backend}"))
                times[backend] = 1e6 * t["rollout"] / (size * args.episodes * 200)
            rows.append([cell, size, f"{times['direct']:.1f}", f"{times['torchrl']:.1f}",
                         f"{times['torchrl'] / times['direct']:.2f}x"])
    if rows:
        table("Collection per member-step (us): the direct loop against TorchRL's Collector",
              ["cell", "R", "direct", "torchrl", "torchrl / direct"], rows)

    if args.before:
        rows = []
        largest = max(size for size in args.sizes if size <= 25)
        for cell in args.cells:
            old = before_solo(args.before, cell, args.episodes)
            per = args.episodes
            old_ms = 1000 * (old["rollout"] + old["train"]) / per
            ours = {size: 1000 * (t["rollout"] + t["train"]) / (size * per) for (c, size, mode), t in timed.items()
                    if c == cell and mode == args.modes[0]}
            rows.append([cell, f"{1000 * old['rollout'] / per:.1f}", f"{1000 * old['train'] / per:.1f}",
                         f"{old_ms:.1f}", f"{ours[1]:.1f}", f"{ours[largest]:.1f}",
                         f"{old_ms / ours[largest]:.2f}x"])
        table(f"Solo runs of commit {args.before} against today's code (ms per member-episode, collecting + "
              "training; process start-up excluded)",
              ["cell", "before: collect", "before: train", "before: total", "today solo",
               f"today R={largest}", f"R={largest} vs before"], rows)

    if args.processes:
        rows, largest, mode = [], max(args.sizes), args.modes[0]
        for cell in args.cells:
            one = timed[cell, largest, mode]["wall"]
            for count in args.processes:
                wall = timed_run(config(cell, largest, args.episodes, f"compile={mode == 'compiled'}",
                                        f"processes={count}"))["wall"]
                rows.append([cell, largest, mode, count, f"{one:.1f}", f"{wall:.1f}", f"{one / wall:.2f}x"])
        table(f"One population over several processes (processes=N; wall time, start-up and compiling included; "
              f"{os.cpu_count()} cores here)",
              ["cell", "R", "mode", "processes", "wall s, one process", "wall s, split", "speed-up"], rows)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.population_speed", main))
