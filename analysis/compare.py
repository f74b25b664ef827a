"""Two reports of the same grid, paired run by run: what a change of code or numerics moved.

    python -m analysis.compare NEW/runs.csv OLD/runs.csv [--markdown OUT.md]
    python -m analysis.compare NEW/runs.csv OLD/runs.csv --cells bro/prioritised sac/prioritised

Runs are paired by (replay mode, algorithm, track seed); each pair's difference is the new
run's final performance minus the old one's. Printed: how many pairs, in how many the new run
is lower, higher or equal, the median and mean difference with a 95% bootstrap interval over
pairs, how many runs collapsed (final below ``--collapse``, 20) in each, and per cell the mean
difference against the cell's combined standard error (how far each cell's mean moved, in the
units a reader of Table 1 compares in). A change meant to keep results must show identical
pairs; a change of rounding shows differences centred on zero (the task's chaos), and a real
change, a shift. ``--cells NEW OLD`` (each ``algo/er``) pairs two different cells by track
instead: one learner against another on the same tracks.
"""

from __future__ import annotations

import argparse
import math
import sys
from engine.names import markdown_cell
from collections import defaultdict
from engine.budget import real
from pathlib import Path


def _refuse(message: str) -> None:
    """One line on stderr and exit status 2, as the other tools refuse."""
    print(f"compare: {message}", file=sys.stderr)
    raise SystemExit(2)


def read_runs(path: Path) -> dict[tuple[str, str, int], float]:
    """{(er, algo, seed): final_mean} of the completed runs of a report's ``runs.csv``."""
    from door import files

    try:
        rows = files.read_csv(path, 1 << 28, "runs.csv")
    except OSError as err:
        _refuse(f"cannot read {path}: {err.strerror}")
    except ValueError as err:  # the file door's refusal (a FIFO, a folder, a file too large)
        _refuse(str(err))
    needed = {"er", "algo", "seed", "status", "final_mean"}
    if not rows or not needed <= set(rows[0]):
        _refuse(f"{path} is not a report's runs.csv (columns {sorted(needed)} expected)")
    runs: dict[tuple[str, str, int], float] = {}
    for line, r in enumerate(rows, start=2):
        if r["status"] != "completed" or r["final_mean"] in ("", None):
            continue
        try:
            key, value = (r["er"], r["algo"], int(r["seed"])), float(r["final_mean"])
        except (TypeError, ValueError):
            _refuse(f"{path} line {line}: seed {r['seed']!r} or final_mean {r['final_mean']!r} is not a number")
        if not math.isfinite(value):
            _refuse(f"{path} line {line}: final_mean {r['final_mean']!r} is not a finite number")
        if key in runs:
            _refuse(f"{path} line {line}: a second completed run of {key[1]}/{key[0]} on track {key[2]}; a report "
                    "lists each run once")
        runs[key] = value
    return runs


def select_cell(runs: dict, cell: str, as_cell: str) -> dict:
    """The runs of ``cell`` (``algo/er``) keyed as ``as_cell``'s, so that two cells pair by track."""
    try:
        (algo, er), (as_algo, as_er) = cell.split("/"), as_cell.split("/")
    except ValueError:
        _refuse(f"a cell is algo/er, e.g. bro/prioritised (got {cell!r} and {as_cell!r})")
    chosen = {(as_er, as_algo, seed): value for (e, a, seed), value in runs.items() if (e, a) == (er, algo)}
    if not chosen:
        cells = sorted({f"{a}/{e}" for e, a, _ in runs})
        _refuse(f"no completed run of cell {cell} (the report has {', '.join(cells) or 'none'})")
    return chosen


def bootstrap_interval(values: list[float], reps: int = 10000, seed: int = 0) -> tuple[float, float]:
    import numpy as np

    x = np.asarray(values)
    if len(x) < 2:
        return float("nan"), float("nan")
    picks = np.random.default_rng(seed).integers(0, len(x), size=(reps, len(x)))
    low, high = np.percentile(x[picks].mean(axis=1), [2.5, 97.5])
    return float(low), float(high)


def _sem(values: list[float]) -> float:
    if len(values) < 2:
        return float("nan")
    mean = sum(values) / len(values)
    return math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1) / len(values))


def compare(new: dict, old: dict, collapse: float = 20.0) -> str:
    keys = sorted(set(new) & set(old))
    if not keys:
        raise SystemExit("compare: the two reports have no run in common (cell and track)")
    diffs = [new[k] - old[k] for k in keys]
    ordered = sorted(diffs)
    mid = len(ordered) // 2
    median = ordered[mid] if len(ordered) % 2 else (ordered[mid - 1] + ordered[mid]) / 2
    low, high = bootstrap_interval(diffs)
    lines = [f"{len(keys)} runs paired ({len(new)} new, {len(old)} old completed runs): the new run is lower in "
             f"{sum(d < 0 for d in diffs)}, higher in {sum(d > 0 for d in diffs)}, equal in "
             f"{sum(d == 0 for d in diffs)}; difference median {median:+.1f}, mean {sum(diffs) / len(diffs):+.1f} "
             f"[{low:+.1f}, {high:+.1f}] (95% bootstrap over runs)",
             f"Collapsed (final below {collapse:g}): {sum(new[k] < collapse for k in keys)} new, "
             f"{sum(old[k] < collapse for k in keys)} old", "",
             "| cell | runs | new mean | old mean | difference | in combined SE |", "|---|---:|---:|---:|---:|---:|"]
    cells = defaultdict(list)
    for k in keys:
        cells[k[:2]].append(k)
    for (er, algo), members in sorted(cells.items()):
        a, b = [new[k] for k in members], [old[k] for k in members]
        diff = sum(a) / len(a) - sum(b) / len(b)
        combined = math.hypot(_sem(a), _sem(b))
        ratio = f"{diff / combined:+.2f}" if combined > 0 else ""
        lines.append(f"| {markdown_cell(f'{algo}/{er}')} | {len(members)} | {sum(a) / len(a):.1f} | {sum(b) / len(b):.1f} | "
                     f"{diff:+.1f} | {ratio} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("new", type=Path, help="the new report's runs.csv")
    parser.add_argument("old", type=Path, help="the old report's runs.csv")
    parser.add_argument("--collapse", type=real(-1e6, 1e6), default=20.0)
    parser.add_argument("--markdown", type=Path, help="also write the comparison to this file")
    parser.add_argument("--cells", nargs=2, metavar=("NEW", "OLD"),
                        help="pair cell NEW of the new report with cell OLD of the old one by track (algo/er each)")
    args = parser.parse_args(argv)
    from engine.tool_output import check_outputs

    check_outputs(parser, reads=[args.new, args.old], markdown=args.markdown)

    new, old = read_runs(args.new), read_runs(args.old)
    heading = ""
    if args.cells:
        new, old = select_cell(new, args.cells[0], args.cells[1]), select_cell(old, args.cells[1], args.cells[1])
        heading = f"New: {args.cells[0]}; old: {args.cells[1]} (the table's cell), paired by track\n"
    text = heading + compare(new, old, args.collapse)
    print(text, end="")
    if args.markdown:
        from door import files

        files.write_text(args.markdown, text)
    return 0


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("analysis.compare", main))
