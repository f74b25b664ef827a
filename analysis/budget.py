"""Where a learner's curve levels off: its final performance after 1x, 3x, ... the paper's budget.

    python -m analysis.budget RUN_DIR... [--budgets 201 603 2010] [--window 20] [--table budget.csv]

A learner without schedules that depend on the run's length (the off-policy learners: their
update schedule counts episodes from the start, their replay memory and temperature do not look
at ``episodes``) computes the same first E episodes whatever ``episodes`` says, so one long run
gives its final performance at every shorter budget E: the mean total reward of training episodes
E - window .. E - 1, which is what a run of E episodes reports as ``final_mean``. Per run folder
(a run, or a population's folder of members) and budget it prints that value, its fraction of the
oracle's score on the run's track (``analysis/data/oracle.csv``, ``oracle_tuning.csv`` for the
tuning tracks), and per budget the mean fraction
over the runs with a 95% bootstrap interval over tracks; the deterministic policy's score at the
end of the run (summary.json's evaluation on its own track) where the run has one, and the mean of
those scores as fractions of the oracle's, with the same interval.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from engine.budget import count
from pathlib import Path

from analysis.report import Run, find_runs, read_oracles


def final_at(rewards: list[float], budget: int, window: int) -> float | None:
    """The final performance a run of ``budget`` episodes reports (mean of its last ``window``), or
    None if the run has fewer episodes."""
    if len(rewards) < budget:
        return None
    last = rewards[budget - min(window, budget):budget]
    return math.fsum(last) / len(last)


def budget_rows(runs: list[Run], budgets: list[int], window: int, oracle: dict[int, float]) -> list[dict]:
    rows = []
    for run in sorted(runs, key=lambda r: (r.algo, r.er, r.seed)):
        own = (run.evaluation or {}).get("own_track")  # the deterministic policy's mean on its track
        for budget in budgets:
            value = final_at(run.rewards, budget, window)
            if value is None:
                continue
            ceiling = oracle.get(run.seed)
            rows.append({"algo": run.algo, "er": run.er, "track": run.seed, "budget": budget, "final": round(value, 6),
                         "oracle": round(ceiling, 6) if ceiling else "",
                         "fraction": round(value / ceiling, 6) if ceiling else "",
                         "evaluation": round(own, 6) if own is not None and budget == len(run.rewards) else ""})
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", type=Path, nargs="+", help="run folders or sweep folders")
    parser.add_argument("--budgets", type=count(1, 1_000_000), nargs="+", default=[201, 603, 2010])
    parser.add_argument("--window", type=count(1, 100_000), default=20, help="episodes averaged (the runs' final_window)")
    parser.add_argument("--table", type=Path, default=None, help="write the rows as CSV")
    args = parser.parse_args(argv)
    from engine.tool_output import check_outputs

    check_outputs(parser, reads=args.folders, table=args.table)

    try:
        runs = [r for r in find_runs(args.folders, say="budget") if r.rewards and r.seed is not None]  # each run once
    except FileNotFoundError as err:
        print(f"budget: {err}", file=sys.stderr)
        return 2
    if not runs:
        print(f"no runs with metrics under {', '.join(map(str, args.folders))}", file=sys.stderr)
        return 1
    oracle = read_oracles()
    rows = budget_rows(runs, args.budgets, args.window, oracle)
    from analysis.compare import bootstrap_interval

    print("| track | " + " | ".join(f"{b} episodes" for b in args.budgets) + " | deterministic, at the end |")
    print("|---:|" + "---:|" * (len(args.budgets) + 1))
    for track in sorted({r["track"] for r in rows}):
        mine = {r["budget"]: r for r in rows if r["track"] == track}
        cells = [(f"{mine[b]['final']:.1f}" + (f" ({mine[b]['fraction']:.3f})" if mine[b]["fraction"] != "" else ""))
                 if b in mine else "" for b in args.budgets]
        end = next((f"{r['evaluation']:.1f}" for r in mine.values() if r["evaluation"] != ""), "")
        print(f"| {track} | " + " | ".join(cells) + f" | {end} |")
    def mean_fraction(label: str, fractions: list[float]) -> None:
        if fractions:
            low, high = bootstrap_interval(fractions)
            print(f"{label}: {statistics.fmean(fractions):.3f} of the oracle [{low:.3f}, {high:.3f}] "
                  f"over {len(fractions)} tracks")

    for budget in args.budgets:
        mean_fraction(f"{budget} episodes", [r["fraction"] for r in rows if r["budget"] == budget and r["fraction"] != ""])
    mean_fraction("deterministic policy at the end",
                  [r["evaluation"] / r["oracle"] for r in rows if r["evaluation"] != "" and r["oracle"] != ""])
    if args.table is not None:
        from engine.outputs import write_table

        write_table(args.table, rows)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("analysis.budget", main))
