"""What the portable numerics cost: training time per cell under ``numerics=native`` and
``numerics=portable`` (``engine/numerics.py``), measured in this run.

    python -m benchmarks.numerics_speed [--episodes 20] [--members 5 25] [--repeats 3]
                                        [--cells spg_p_multi/hybrid ppo/recent sac/memory]

The mode is fixed when torch loads, so each measurement is a child process (this script with
``--child``); the modes alternate, ``--repeats`` times, and the table keeps each one's fastest
repeat (the machine's noise only ever adds time). Times are per member-episode, collection and
training together, start-up excluded; one thread, as training runs use. The last column is the
ratio portable / native: what a sweep pays for results that rerun bit for bit on any x86-64
CPU with AVX2.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CELLS = ["spg_p_multi/hybrid", "ppo/recent", "sac/memory"]
TRACKS = [2067791, 5468063, 5412436, 8273186, 773203]


def child(mode: str, cell: str, members: int, episodes: int) -> None:
    """Train one population in this process under ``mode``; print its timed phases as JSON."""
    from engine import numerics

    numerics.apply(mode)
    from engine.config import RunConfig
    from engine.runner import train_population

    algo, er = cell.split("/")
    seeds = [*TRACKS, *range(1000, 1000 + max(0, members - len(TRACKS)))][:members]
    extra = ["algo.td.warmup_episodes=1"] if algo in ("sac", "td3") else []
    cfg = RunConfig.compose(f"algo={algo}", f"er={er}", f"seeds=[{','.join(map(str, seeds))}]",
                            f"episodes={episodes}", "progress=false", "logger=none", "checkpoint_every=0",
                            f"numerics={mode}", *extra)
    with tempfile.TemporaryDirectory() as out:
        summary = train_population(cfg, Path(out))[0]
    print(json.dumps({"seconds": summary["time/rollout_s"] + summary["time/train_s"],
                      "numerics": summary["numerics"]}))


def measure(mode: str, cell: str, members: int, episodes: int) -> dict:
    env = {**os.environ, "RL_LOGGING_LEVEL": "WARNING", "PYTHONWARNINGS": "ignore"}
    result = subprocess.run([sys.executable, "-m", "benchmarks.numerics_speed", "--child", mode, cell,
                             str(members), str(episodes)], cwd=ROOT, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"{mode} {cell} R={members} failed:\n{result.stderr[-2000:]}")
    return json.loads(result.stdout.splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--members", type=int, nargs="+", default=[5, 25])
    parser.add_argument("--cells", nargs="+", default=CELLS)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--child", nargs=4, metavar=("MODE", "CELL", "MEMBERS", "EPISODES"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        mode, cell, members, episodes = args.child
        child(mode, cell, int(members), int(episodes))
        return 0
    from benchmarks.train_speed import table

    rows, kernels = [], {}
    for cell in args.cells:
        for members in args.members:
            best = {"native": float("inf"), "portable": float("inf")}
            for _ in range(args.repeats):
                for mode in best:
                    result = measure(mode, cell, members, args.episodes)
                    best[mode] = min(best[mode], result["seconds"])
                    kernels[mode] = result["numerics"]
            per = 1000 / (members * args.episodes)
            rows.append([cell, members, f"{best['native'] * per:.1f}", f"{best['portable'] * per:.1f}",
                         f"{best['portable'] / best['native']:.2f}x"])
    print(f"{args.episodes} episodes per run, one thread, best of {args.repeats} alternated repeats; "
          + "; ".join(f"{mode}: {k['kernels']} kernels, MKL branch {k['mkl_branch']}" for mode, k in kernels.items()))
    table("Training per member-episode (ms, collection and training), native against portable numerics",
          ["cell", "R", "native", "portable", "portable / native"], rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
