"""Lay out a sweep's results beside the paper's: ``python report.py SWEEP_DIR``.

Writes into ``SWEEP_DIR/report/``:
- ``runs.csv``: one row per run (cell, track seed, status, final performance, code version, and
  where the oracle scored the track (``analysis/data/oracle.csv``) its score and the run's
  oracle-normalised score);
- ``table.md``, ``table.csv``: Table 1's layout, mean ± standard error over seeds of each run's
  final performance with the cell's budget (episodes), the paper's value, and the difference in
  units of the combined standard error, for cells whose runs are of the paper's 201 episodes only
  (other budgets are shown, not compared; a cell mixing budgets says so); diverged runs counted;
- ``conclusions.md``: the paper's three conclusions as effects paired by track with 95%
  bootstrap intervals over tracks and a verdict, on the paper's five tracks and on all tracks;
- ``collapse.md``: per cell, the runs whose final performance is below 20 (collapsed);
- ``iqm.md`` and ``iqm.png``: interquartile mean of the runs' final performances per cell
  (one score per run) with 95% bootstrap intervals over runs (tracks);
- ``beyond.md`` (if the sweep has SAC, TD3, prioritised-replay or Stable-Baselines3 runs): those cells and the paper's
  best and PPO cells, with IQM intervals over runs, paired differences from the paper's best cell and
  wall time per run; ``generalisation.md`` (if runs were evaluated on ``eval_seeds``): own-track and
  unseen-track scores and their gap, for fixed- and random-track training; ``normalised.md`` (if
  the oracle scored the runs' tracks): each cell's final performance on the oracle's scale, 0 for a
  car that stands still and 1 for the oracle (``evaluate.py --oracle``) on the run's track;
- ``statistics.md``, ``profiles.png``, ``improvement.png``: the cells as rliable reports them
  (``analysis/statistics.py``): IQM, mean and optimality gap with stratified bootstrap
  intervals, performance profiles, and the probability of improvement for the pairs the paper's
  conclusions compare;
- ``curves_*.png``: learning curves, mean over tracks with a ±1 SE band, per algorithm and per
  replay mode; ``paper_tracks.png``; ``agent.png``, a frame of the best run's policy.
Lists runs that are partial (killed or running), damaged (with the file and the reason;
``engine/rundir.py``) or diverged. The figures need the
``render`` extra; without it only the tables are written.

Every report states the code version (commit and source hash, from each run's summary.json)
and the numerics (mode and kernels, ``engine/numerics.py``, and whether the update steps were
compiled, ``compile=true``) that made its runs. Runs of
different code versions are refused unless ``--allow-mixed-versions`` is given, runs of different
numerics unless ``--allow-mixed-numerics`` is given; then every group is listed with its number of runs.
"""

from __future__ import annotations

import argparse
import sys
from engine.names import markdown_cell
from pathlib import Path

from engine import numerics
from door import files
from analysis.beyond import beyond_markdown, generalisation_markdown
from analysis.report import (cells, code_versions, collapse_markdown, conclusions_markdown, find_runs,
                             normalised_markdown, numerics_groups, read_oracle, read_paper_table, table_markdown,
                             versions_markdown, write_runs_csv, write_table_csv)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sweep_dir", type=Path, help="a sweep folder, e.g. outputs/sweeps/paper_grid")
    parser.add_argument("--no-figures", action="store_true", help="write the tables only")
    parser.add_argument("--allow-mixed-versions", action="store_true",
                        help="report runs made by different versions of the code together")
    parser.add_argument("--allow-mixed-numerics", action="store_true",
                        help="report runs made under different numerics (modes or kernels) together")
    args = parser.parse_args(argv)
    from engine.tool_output import check_output_folder

    check_output_folder(parser, "sweep_dir", args.sweep_dir / "report")  # its outputs: never inside a run's folder
    try:
        runs = find_runs(args.sweep_dir, say="report")  # each run once: a copy or link named, not counted
    except FileNotFoundError as err:
        print(f"report: {err}", file=sys.stderr)
        return 2
    versions = code_versions(runs)
    if len(versions) > 1 and not args.allow_mixed_versions:
        print(f"report: {args.sweep_dir} holds runs of {len(versions)} versions of the code; a table "
              "mixing them describes no single program. Versions (source hash: runs, e.g.):", file=sys.stderr)
        for key, members in versions.items():
            print(f"  {key}: {len(members)} runs, e.g. {members[0].path}", file=sys.stderr)
        print("Re-run the sweep from one commit (clean_sweep.py), or pass --allow-mixed-versions.",
              file=sys.stderr)
        return 2
    modes = numerics_groups(runs)
    if len(modes) > 1 and not args.allow_mixed_numerics:
        print(f"report: {args.sweep_dir} holds runs of {len(modes)} numerics (engine/numerics.py; compiled or "
              "eager update steps round differently too); a table mixing them has no single way to rerun. "
              "Numerics (runs, e.g.):", file=sys.stderr)
        for key, members in modes.items():
            print(f"  {key}: {len(members)} runs, e.g. {members[0].path}", file=sys.stderr)
        print("Re-run the sweep under one numerics= and compile= setting, or pass --allow-mixed-numerics.",
              file=sys.stderr)
        return 2
    mode = next(iter(modes)).split(" ")[0] if len(modes) == 1 else numerics.DEFAULT
    try:  # only the agent frame computes (a policy's episode): in the runs' mode, before torch loads
        numerics.apply(mode if mode in numerics.MODES else numerics.DEFAULT)
    except numerics.NumericsError as err:
        print(f"report: the agent frame is drawn under this process's numerics ({err})")
    out = files.folder(args.sweep_dir / "report", args.sweep_dir, create=True)  # a real folder, not a link
    every = runs
    runs = [r for r in runs if r.track_mode == "fixed"]  # Table 1 and its conclusions: fixed-track training
    table = cells(runs, read_paper_table())
    markdown = versions_markdown(versions) + "\n" + table_markdown(table)
    files.write_text(out / "table.md", markdown)
    write_table_csv(table, out / "table.csv")
    oracle = read_oracle()
    write_runs_csv(every, out / "runs.csv", args.sweep_dir, oracle)
    files.write_text(out / "conclusions.md", versions_markdown(versions) + "\n" + conclusions_markdown(runs))
    files.write_text(out / "collapse.md", versions_markdown(versions) + "\n" + collapse_markdown(runs))
    print(markdown)
    for status in ("diverged", "partial", "damaged"):
        listed = [r for r in every if r.status == status]
        if listed:
            print(f"{len(listed)} {status} run(s), not in the tables:" if status != "diverged"
                  else f"{len(listed)} diverged run(s):")
            for r in listed:
                print(f"  {r.path} ({len(r.rewards)} episodes in metrics.csv)"
                      + (f": {r.problem}" if r.problem else ""))
    extra = []
    from analysis.statistics import statistics_markdown

    for name, text in (("beyond.md", beyond_markdown(every)), ("generalisation.md", generalisation_markdown(every)),
                       ("normalised.md", normalised_markdown(runs, oracle)),
                       ("statistics.md", statistics_markdown(runs, oracle))):
        if text:
            files.write_text(out / name, versions_markdown(versions) + "\n" + text)
            print(text)
            extra.append(name)
    unsealed = sum(r.status in ("completed", "diverged") and not r.sealed for r in every)
    if unsealed:
        print(f"{unsealed} finished run(s) written before summaries were sealed (engine/legacy_summaries.txt): "
              "their metrics and weights are checked against their records where they have them, their "
              "summaries' own values are not")
    print(f"{sum(r.status == 'completed' for r in every)} completed runs; wrote {out}/table.md, table.csv, "
          "runs.csv, conclusions.md, collapse.md" + "".join(f", {name}" for name in extra))
    if not args.no_figures:
        write_figures(runs, out, oracle)
    return 0


def write_figures(runs, out: Path, oracle: dict[int, float] | None = None) -> None:
    try:
        from analysis import figures as figures
        from racing.figures import import_pyplot

        import_pyplot()  # matplotlib itself, which the figures import only when they draw
    except ImportError:
        print("figures skipped: they need matplotlib (the render extra: pip install -c constraints/cpu.txt "
              "-e '.[render]'); the tables above are complete")
        return
    rows = figures.iqm_rows(runs)
    lines = ["IQM of the runs' final performances per cell; 95% interval from resampling runs (tracks).", "",
             "| cell | IQM | 95% CI | runs |", "|---|---:|---|---:|"]
    lines += [f"| {markdown_cell(label)} | {point:.1f} | " + (f"[{low:.1f}, {high:.1f}]" if n > 1 else "n/a (one run)") + f" | {n} |"
              for label, point, low, high, n in rows]
    files.write_text(out / "iqm.md", "\n".join(lines) + "\n")
    written = figures.learning_curve_figures(runs, out)
    frontier = figures.frontier_figure(runs, read_oracle(), out / "curves_beyond.png")
    written += [frontier] if frontier is not None else []
    from analysis.statistics import statistics_figures

    written += statistics_figures(runs, oracle or {}, out)
    written += [p for p in (figures.iqm_figure(rows, out / "iqm.png"),
                            figures.paper_tracks_figure(out / "paper_tracks.png")) if p is not None]
    written += agent_frame(runs, out, figures)
    print(f"wrote iqm.md and {len(written)} figures")


def agent_frame(runs, out: Path, figures) -> list[Path]:
    """A frame of the best completed run whose policy loads; none (with a note) otherwise."""
    from engine.evaluation import RunFolderError

    finished = sorted((r for r in runs if r.status == "completed" and r.final_mean is not None),
                      key=lambda r: r.final_mean, reverse=True)
    for run in finished:
        try:
            return [figures.agent_frame(run.path, out / "agent.png")]
        except RunFolderError as err:
            print(f"agent frame: skipping {run.path}: {err}")
    print("agent frame: no completed run with a loadable policy")
    return []


if __name__ == "__main__":
    from engine.processes import run_tool

    raise SystemExit(run_tool("report", main))
