"""The decisive experiment's reading (docs/results/caution/README.md): runs started from a fast policy
(``algo.td.start_from``) that scored their deterministic policy every few episodes (``eval_every``).

    python -m analysis.caution SWEEP_OR_RUNS... [--last 5] [--table caution.csv]

Per run, as fractions of the oracle's score on its track (``analysis/data/oracle*.csv``): S0, the first
evaluation (the started policy while its actor is held: ``algo.td.critic_first_episodes`` covers it), the
lowest evaluation after it, S_end (the mean of the last ``--last`` evaluations) and the drift S_end - S0;
the training metric (summary.json's final performance). Then per configuration (the run's folder's last
three names: ``<sweep>/<algo>/<er>``) the mean over its tracks (the drift with its 95% t interval over them), and the reading the README fixed before the runs:
"prefers caution" if every track drifts by -0.010 or lower, "holds" if the mean drift is -0.005 or higher
and no track is below -0.010, else "mixed".
"""

from __future__ import annotations

import argparse
import math
import sys
from engine.budget import count
from pathlib import Path

CAUTION, HOLDS = -0.010, -0.005  # the README's thresholds, in fractions of the oracle
COLUMNS = ("configuration", "track", "s0", "lowest", "s_end", "drift", "training", "evaluations")


def run_rows(runs: list[Path], oracle: dict, last: int = 5) -> list[dict]:
    from door import files
    from engine.outputs import read_summary

    from engine.config import RunConfig

    rows, configurations = [], {}
    for run in runs:  # each run once (engine.runset)
        summary = read_summary(run)
        settings = summary.get("settings") or {}
        if not summary.get("start"):
            raise ValueError(f"{run} did not start from another policy (algo.td.start_from): its first evaluation is "
                             "no start's score")
        td, every = (settings.get("algo") or {}).get("td") or {}, settings.get("eval_every") or 0
        if td.get("critic_first_episodes", 0) < every - 1:
            raise ValueError(f"{run}: its first evaluation (after episode {every - 1}) comes after its actor moved "
                             f"(algo.td.critic_first_episodes={td.get('critic_first_episodes', 0)}), so it is not the "
                             "start's score")
        name = "/".join(p for p in run.parent.parts[-3:] if p != "/")
        same = {k: v for k, v in RunConfig.run_settings(settings).items() if k not in ("seed", "seeds")}
        if configurations.setdefault(name, (same, run))[0] != same:
            raise ValueError(f"{configurations[name][1]} and {run} are read as one configuration ({name}) but differ "
                             "in settings besides the track; give their folders separately")
        track = summary["seed"]
        o = oracle.get(track)
        if o is None:
            raise ValueError(f"{run}: no oracle score for track {track} (analysis/data/oracle*.csv)")
        table = files.read_csv(run / "metrics.csv", 64 * 2**20, "metrics")
        scored = [(int(r["episode"]), float(r["deterministic"])) for r in table if r.get("deterministic")]
        if len(scored) < last + 1:
            raise ValueError(f"{run}: {len(scored)} evaluations of the deterministic policy; the reading needs "
                             f"at least {last + 1} (train with eval_every)")
        s0, end = scored[0][1], math.fsum(v for _, v in scored[-last:]) / last
        rows.append({"configuration": name, "track": track,
                     "s0": s0 / o, "lowest": min(v for _, v in scored[1:]) / o, "s_end": end / o,
                     "drift": (end - s0) / o, "training": summary["final_mean"] / o,
                     "evaluations": len(scored)})
    return rows


def reading(drifts: list[float]) -> str:
    if all(d <= CAUTION for d in drifts):
        return "prefers caution"
    if sum(drifts) / len(drifts) >= HOLDS and min(drifts) >= CAUTION:
        return "holds"
    return "mixed"


def summary_rows(rows: list[dict]) -> list[dict]:
    """Per configuration: the means over its tracks, the drift's 95% t interval over them, the reading."""
    from analysis.factors import t_interval

    out = []
    for name in sorted({r["configuration"] for r in rows}):
        mine = [r for r in rows if r["configuration"] == name]
        mean = {k: math.fsum(r[k] for r in mine) / len(mine) for k in ("s0", "lowest", "s_end", "drift", "training")}
        _, low, high = t_interval([r["drift"] for r in mine])  # each track's drift is a paired difference
        out.append({"configuration": name, "tracks": len(mine), **mean, "drift_low": low, "drift_high": high,
                    "reading": reading([r["drift"] for r in mine])})
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("paths", type=Path, nargs="+", help="run folders, or sweep folders holding them")
    parser.add_argument("--last", type=count(1, 10_000), default=5, help="evaluations averaged into S_end (default 5)")
    parser.add_argument("--table", type=Path, default=None, help="also write the per-run rows as CSV")
    args = parser.parse_args(argv)
    from engine.tool_output import check_outputs

    check_outputs(parser, reads=args.paths, table=args.table)
    from analysis.report import read_oracles
    from engine.outputs import RunFolderError
    from engine.runset import read_runs

    try:
        rows = run_rows(read_runs(args.paths, say="caution").runs, read_oracles(), args.last)
    except (RunFolderError, ValueError) as err:
        print(f"caution: {err}", file=sys.stderr)
        return 2
    show = lambda v: f"{v:.3f}" if isinstance(v, float) else str(v)
    print("| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS))
    for row in rows:
        print("| " + " | ".join(show(row[c]) for c in COLUMNS) + " |")
    summaries = summary_rows(rows)
    keys = list(summaries[0])
    print("\n| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for row in summaries:
        print("| " + " | ".join(show(row[k]) for k in keys) + " |")
    if args.table is not None:
        from engine.outputs import write_table

        write_table(args.table, rows)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("analysis.caution", main))
