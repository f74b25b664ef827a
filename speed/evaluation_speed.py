"""A saved policy's time per step on one torch thread against torch's default (one per core).

    python -m speed.evaluation_speed RUN [RUN ...] [--steps 200] [--rounds 3] [--side-by-side]

For each run folder (``train.py``'s; the policy ``score.py`` would load), in fresh processes: the
milliseconds per deterministic step on a generated track (seed 1001, start seed 0; the episode
restarts when it ends), after 20 steps not timed. The two thread counts alternate, ``--rounds``
times each, and the table gives each one's median and the default's over one thread's.
``--side-by-side`` runs two copies of each measurement at once (as two ``score.py`` runs share a
two-core machine) and takes their mean. Every tool runs on one thread (``engine.numerics.apply``).
"""

from __future__ import annotations

from engine.budget import STEPS, count
import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

MEASURE = """
import json, sys, time
from pathlib import Path
from engine import numerics
numerics.apply(numerics.DEFAULT, int(sys.argv[2]))
import torch
from engine.evaluation import deterministic_action, load_policy, make_env
policy, settings = load_policy(Path(sys.argv[1]))
env = make_env(settings, 1001)
steps = int(sys.argv[3])
obs, _ = env.reset(seed=0)
policy.reset()
def drive(n):
    global obs
    for _ in range(n):
        obs, _, terminated, truncated, _ = env.step(deterministic_action(policy, obs))
        if terminated or truncated:
            obs, _ = env.reset(seed=0)
            policy.reset()
drive(20)
start = time.perf_counter()
drive(steps)
print(json.dumps({"ms": 1000 * (time.perf_counter() - start) / steps, "threads": torch.get_num_threads()}))
"""


def measure(run: str, threads: int, steps: int, copies: int) -> tuple[float, int]:
    """Milliseconds per step (the mean of ``copies`` processes run at once) and the threads torch ran."""
    root = Path(__file__).resolve().parent.parent
    procs = [subprocess.Popen([sys.executable, "-c", MEASURE, str(Path(run).resolve()), str(threads), str(steps)], cwd=root,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(copies)]
    results = []
    for proc in procs:
        out, err = proc.communicate()
        if proc.returncode != 0:
            raise SystemExit(f"evaluation_speed: measuring {run} failed:\n{err[-2000:]}")
        results.append(json.loads(out.strip().splitlines()[-1]))
    return statistics.mean(r["ms"] for r in results), results[0]["threads"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", metavar="RUN", help="run folders (train.py's)")
    parser.add_argument("--steps", type=STEPS, default=200, help="steps timed per measurement")
    parser.add_argument("--rounds", type=count(1, 1000), default=3, help="measurements per thread count, alternated")
    parser.add_argument("--side-by-side", action="store_true", help="two copies of each measurement at once")
    args = parser.parse_args(argv)
    if args.steps < 1 or args.rounds < 1:
        parser.error("--steps and --rounds must be >= 1")
    for run in args.runs:
        if not Path(run, "summary.json").is_file():
            parser.error(f"{run} is not a finished run folder (no summary.json)")
    default = os.cpu_count() or 1
    copies = 2 if args.side_by_side else 1
    print(f"ms per deterministic step, {args.steps} steps, median of {args.rounds} alternated measurements"
          + (", two processes at once" if copies == 2 else "") + f"; {default} cores")
    print(f"{'run':<44} {'1 thread':>9} {f'{default} threads':>11} {'default / 1':>12}")
    for run in args.runs:
        times: dict[int, list[float]] = {1: [], default: []}
        for _ in range(args.rounds):
            for threads in times:
                ms, ran = measure(run, threads, args.steps, copies)
                if ran != threads:
                    raise SystemExit(f"evaluation_speed: asked for {threads} threads, torch ran {ran}")
                times[threads].append(ms)
        one, many = statistics.median(times[1]), statistics.median(times[default])
        print(f"{run[-44:]:<44} {one:>9.2f} {many:>11.2f} {many / one:>12.2f}")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("speed.evaluation_speed", main))
