"""What each fast path saves over a whole run: the rule that decides whether a fused copy stays.

    python -m speed.fast_path_savings [--learners sac tqc crossq td3 spg_p_multi ppo] [--episodes 12]
                                      [--members 5] [--repeats 3]

For each learner, whole training runs (a population of ``--members`` on the paper's first tracks,
``--episodes`` episodes, the default numerics, one thread) alternate between its fast path and its
loss module (``FUSED`` off in the learner's family), each in a fresh process (so neither inherits the
other's caches), A/B/A/B... The table gives the median CPU seconds of each and the saving: the share
of the loss module's run the fast path saves. A copy saving less than about 5% of a whole run is not
worth its guard (``learners.fast_paths``): delete it. Off-policy runs warm up for one episode (their
updates are most of a run's cost; ``algo.td.warmup_episodes=1``), so a short run weighs its updates as
a full one does.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from engine.budget import EPISODES, count
from pathlib import Path

LEARNERS = ("sac", "tqc", "crossq", "td3", "spg_p_multi", "ppo")
TRACKS = (2067791, 5468063, 773203, 1324412, 4064233)  # seeds of the paper's runs, one member each


def one_run(learner: str, fused: bool, episodes: int, members: int, folder: str) -> float:
    """One run in this process; its CPU seconds (every thread), from the run's own record."""
    from engine import numerics

    numerics.apply(numerics.DEFAULT)
    from engine.runner import train_population
    from learners.monte_carlo import learner as monte_carlo
    from learners.registry import spec
    from learners.td import learner as td
    from tests.test_config import load

    td.FUSED = monte_carlo.FUSED = fused
    overrides = [f"algo={learner}", "er=memory", f"episodes={episodes}", "progress=false", "logger=none",
                 f"seeds=[{','.join(map(str, TRACKS[:members]))}]"]
    if spec(load(f"algo={learner}").algo.loss).family == "td":
        overrides.append("algo.td.warmup_episodes=1")
    summaries = train_population(load(*overrides), Path(folder))
    paths = summaries[0]["paths"][0]
    if (paths["critic"] == "fused") != fused:
        raise SystemExit(f"{learner}: asked for fused={fused}, ran {paths}")
    return float(summaries[0]["cpu_time_s"])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m speed.fast_path_savings", description=__doc__.split("\n\n")[0])
    parser.add_argument("--learners", nargs="+", default=list(LEARNERS))
    parser.add_argument("--episodes", type=EPISODES, default=12)
    parser.add_argument("--members", type=count(1, 1000), default=5)
    parser.add_argument("--repeats", type=count(1, 1000), default=3)
    parser.add_argument("--one", nargs=2, metavar=("LEARNER", "PATH"), help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(one_run(args.one[0], args.one[1] == "fused", args.episodes, args.members, args.out)))
        return 0
    rows = []
    for learner in args.learners:
        seconds: dict[str, list[float]] = {"fused": [], "module": []}
        for repeat in range(args.repeats):
            for path in ("fused", "module") if repeat % 2 == 0 else ("module", "fused"):
                with tempfile.TemporaryDirectory() as folder:
                    done = subprocess.run([sys.executable, "-m", "speed.fast_path_savings", "--one", learner, path,
                                           "--episodes", str(args.episodes), "--members", str(args.members),
                                           "--out", str(Path(folder) / "run")], capture_output=True, text=True)
                if done.returncode != 0:
                    print(done.stderr, file=sys.stderr)
                    return done.returncode
                seconds[path].append(float(done.stdout.strip().splitlines()[-1]))
        fused, module = statistics.median(seconds["fused"]), statistics.median(seconds["module"])
        rows.append((learner, fused, module, 1 - fused / module))
        print(f"{learner}: fused {seconds['fused']}, module {seconds['module']}", file=sys.stderr, flush=True)
    print(f"\nWhole runs: {args.members} members, {args.episodes} episodes, median of {args.repeats} "
          "(CPU s, fresh processes, alternated)\n")
    print("| learner | fused | loss module | saved |")
    print("|---|---:|---:|---:|")
    for learner, fused, module, saved in rows:
        print(f"| {learner} | {fused:.1f} | {module:.1f} | {saved:.1%} |")
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    sys.exit(run_tool("speed.fast_path_savings", main))
