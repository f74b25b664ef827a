"""Lay out a sweep's results beside the paper's: ``python report.py SWEEP_DIR``.

Writes ``SWEEP_DIR/report/table.md`` and ``table.csv`` (Table 1's layout: mean ± standard
error over seeds of each run's final performance, the paper's value, and the difference in
units of the combined standard error), and lists runs that are partial, unreadable or diverged.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from experiment.report import cells, find_runs, read_paper_table, table_markdown, write_table_csv


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_dir", type=Path, help="a sweep folder, e.g. outputs/sweeps/paper_grid")
    args = parser.parse_args(argv)
    try:
        runs = find_runs(args.sweep_dir)
    except FileNotFoundError as err:
        print(f"report: {err}", file=sys.stderr)
        return 2
    out = args.sweep_dir / "report"
    out.mkdir(exist_ok=True)
    table = cells(runs, read_paper_table())
    markdown = table_markdown(table)
    (out / "table.md").write_text(markdown)
    write_table_csv(table, out / "table.csv")
    print(markdown)
    for status in ("diverged", "partial", "unreadable"):
        listed = [r for r in runs if r.status == status]
        if listed:
            print(f"{len(listed)} {status} run(s):")
            for r in listed:
                print(f"  {r.path} ({len(r.rewards)} episodes in metrics.csv)")
    print(f"{sum(r.status == 'completed' for r in runs)} completed runs; wrote {out}/table.md, table.csv")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
