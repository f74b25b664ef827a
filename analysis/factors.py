"""One factor at a time against a base, paired by track: what each configuration of a tuning sweep changes.

    python -m analysis.factors SWEEP_DIR --base gamma0.9 [--markdown factors.md] [--table factors.csv]

A configuration is a folder under ``SWEEP_DIR`` whose runs (one per track; a population's members)
share it, named as the sweep's ``hydra.sweep.subdir`` made it (``gamma0.99``, ``entropy-4``, ...); the
base is one of them. Per configuration: the final performance on each track (the last 20 training
episodes), their mean, the mean difference from the base paired by track with a 95% t interval over
the tracks (few tracks give a wide one: that is what they can say), the deterministic policy's score
on its own track (summary.json's evaluation) and both as fractions of the oracle's score on each track
(``analysis/data``), collapses (final < 20) and CPU-minutes per run. Runs must be finished (``--running``
leaves out, and names, the configurations still training or stopped); a configuration with a diverged run
gets its row without a mean or a difference (a diverged run's final performance is no result); a damaged
run, or a configuration missing a track of the base's, is refused.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from engine.names import markdown_cell
from pathlib import Path

from analysis.report import find_runs, read_oracles

# two-sided 95% quantiles of Student's t by degrees of freedom (1..30), then the normal's
_T95 = [12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160, 2.145, 2.131,
        2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056, 2.052, 2.048, 2.045, 2.042]
COLLAPSE = 20.0
# a configuration's columns after its tracks' (a row with a diverged run leaves them empty)
SUMMARY_COLUMNS = ("mean", "vs base", "95% low", "95% high", "of the oracle", "deterministic, of the oracle",
                   "collapsed", "CPU-min per run")


def t_interval(differences: list[float]) -> tuple[float, float, float]:
    """(mean, low, high): the mean of ``differences`` with its two-sided 95% t interval (one value: no interval)."""
    mean = math.fsum(differences) / len(differences)
    if len(differences) < 2:
        return mean, math.nan, math.nan
    half = (_T95[len(differences) - 2] if len(differences) - 1 <= len(_T95) else 1.96) * \
        statistics.stdev(differences) / math.sqrt(len(differences))
    return mean, mean - half, mean + half


def configurations(sweep: Path, running: bool = False) -> dict[str, dict[int, object]]:
    """{configuration: {track: run}} of the finished runs under ``sweep`` (``running``: configurations with
    a run still training, or stopped, are left out, each named on stderr; else refused). A damaged run is
    always refused."""
    found: dict[str, dict[int, object]] = {}
    unfinished: dict[str, str] = {}
    for run in find_runs(sweep):
        parts = run.path.relative_to(sweep).parts
        if not parts:
            raise ValueError(f"{sweep} is a run's folder, not a sweep's: give the folder whose subfolders are the "
                             "configurations (each holding its runs)")
        name = parts[0]
        if run.status == "damaged":
            raise ValueError(f"{run.path} is damaged ({run.problem}); repair or remove it")
        if run.status not in ("completed", "diverged"):
            if running:
                unfinished[name] = f"{run.path.name} {run.status}"
                continue
            raise ValueError(f"{run.path} is not finished ({run.status}); wait for it, resume it, or pass --running to "
                             "leave its configuration out")
        if run.seed in found.setdefault(name, {}):
            raise ValueError(f"{name} holds two runs of track {run.seed}")
        found[name][run.seed] = run
    for name, why in sorted(unfinished.items()):
        print(f"analysis.factors: left out {name} ({why}: not finished)", file=sys.stderr)
    return {name: runs for name, runs in found.items() if name not in unfinished}


def factor_rows(sweep: Path, base: str, oracle: dict[int, float] | None = None, running: bool = False) -> list[dict]:
    configs = configurations(Path(sweep), running)
    if base not in configs:
        raise ValueError(f"no configuration {base!r} under {sweep}; found {', '.join(sorted(configs))}")
    oracle = read_oracles() if oracle is None else oracle
    tracks = sorted(configs[base])
    rows = []
    for name in [base, *sorted(set(configs) - {base})]:
        runs = configs[name]
        missing = [t for t in tracks if t not in runs]
        if missing:
            raise ValueError(f"{name} has no run of track(s) {missing} that the base {base} has")
        diverged = [t for t in tracks if runs[t].status == "diverged" or configs[base][t].status == "diverged"]
        if diverged:  # a diverged run's final performance is not a result (report.py leaves it out too)
            rows.append({"configuration": name, **{f"track {t}": "diverged" if runs[t].status == "diverged"
                                                   else round(runs[t].final_mean, 2) for t in tracks},
                         **dict.fromkeys(SUMMARY_COLUMNS, ""),
                         "diverged": sum(runs[t].status == "diverged" for t in tracks)})
            continue
        finals = [runs[t].final_mean for t in tracks]
        mean, low, high = t_interval([runs[t].final_mean - configs[base][t].final_mean for t in tracks])
        own = [(runs[t].evaluation or {}).get("own_track") for t in tracks]
        fractions = [runs[t].final_mean / oracle[t] for t in tracks if t in oracle]
        det = [o / oracle[t] for o, t in zip(own, tracks) if o is not None and t in oracle]
        cpu = [runs[t].cpu_time for t in tracks if runs[t].cpu_time is not None]
        rows.append({"configuration": name, **{f"track {t}": round(f, 2) for t, f in zip(tracks, finals)},
                     "mean": round(math.fsum(finals) / len(finals), 2),
                     "vs base": "" if name == base else round(mean, 2),
                     "95% low": "" if name == base else round(low, 2),
                     "95% high": "" if name == base else round(high, 2),
                     "of the oracle": round(math.fsum(fractions) / len(fractions), 4) if len(fractions) == len(tracks)
                     else "",
                     "deterministic, of the oracle": round(math.fsum(det) / len(det), 4) if len(det) == len(tracks)
                     else "",
                     "collapsed": sum(f < COLLAPSE for f in finals),
                     "CPU-min per run": round(math.fsum(cpu) / len(cpu) / 60, 2) if cpu else "", "diverged": 0})
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as a Markdown table, the difference from the base with its interval in one column."""
    keys = [k for k in rows[0] if k not in ("95% low", "95% high")]
    lines = ["| " + " | ".join(keys) + " |", "|---" + "|---:" * (len(keys) - 1) + "|"]
    for row in rows:
        def cell(k):
            if k != "vs base":
                return markdown_cell(str(row[k]))
            if row[k] == "":
                return "(base)" if row is rows[0] else ""
            if math.isnan(row["95% low"]):  # one track: no interval
                return f"{row[k]:+.2f}"
            return f"{row[k]:+.2f} [{row['95% low']:+.2f}, {row['95% high']:+.2f}]"
        cells = [cell(k) for k in keys]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep", type=Path, help="a sweep folder: one subfolder per configuration")
    parser.add_argument("--base", required=True, help="the configuration the others are paired against")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the table to this file")
    parser.add_argument("--table", type=Path, default=None, help="write the rows as CSV")
    parser.add_argument("--running", action="store_true", help="leave out configurations still running")
    args = parser.parse_args(argv)
    from engine.tool_output import check_outputs

    check_outputs(parser, reads=[args.sweep], markdown=args.markdown, table=args.table)

    for path in (args.markdown, args.table):
        if path is not None and not path.parent.is_dir():
            print(f"analysis.factors: {path.parent} is not a folder; give a file in an existing folder", file=sys.stderr)
            return 2
    try:
        rows = factor_rows(args.sweep, args.base, running=args.running)
    except (ValueError, FileNotFoundError) as err:
        print(f"analysis.factors: {err}", file=sys.stderr)
        return 2
    text = markdown(rows)
    print(text, end="")
    if args.markdown:
        from door import files

        files.write_text(args.markdown, text)
    if args.table:
        from engine.outputs import write_table

        write_table(args.table, rows)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("analysis.factors", main))
