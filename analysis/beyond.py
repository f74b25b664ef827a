"""Beyond the paper: other algorithms against the paper's best cell, and generalisation.

``beyond_markdown``: per cell (SAC, TD3, with uniform or prioritised replay, the paper's best
cell and its PPO cells, Stable-Baselines3's runs from ``baseline.py``, and any other cell in the sweep), on the paper's five tracks and on all
tracks: runs, mean ± SE of the final performance, IQM with a 95% bootstrap interval over runs,
the difference from the paper's best cell paired by track (95% bootstrap interval over tracks,
with a verdict on at least ``MIN_VERDICT_TRACKS`` tracks), collapsed runs (final performance
below 20), diverged runs, and wall time per run. Only runs trained on fixed tracks count here.

``generalisation_markdown``: per cell and training-track mode (``env.track`` fixed or random),
the final deterministic policy's score on its own track and on the unseen evaluation tracks
(``eval_seeds``, from summary.json's "evaluation"), and the gap between them; on the paper's
five tracks and, when runs were evaluated on more, on all of them.
"""

from __future__ import annotations

import math

import numpy as np

from engine.names import markdown_cell
from analysis.aggregate import iqm, stratified_bootstrap_ci
from analysis.report import (ALGO_COLUMNS, ALGO_TITLES, COLLAPSE_BELOW, MIN_VERDICT_TRACKS, PAPER_SEEDS, Run,
                             _mean_difference, paired_bootstrap, paired_sign)

REFERENCE = ("memory", "spg_p_multi")  # the paper's best cell (Table 1: 141.1)
ROWS = (("memory", "sac"), ("memory", "sac_sb3"), ("memory", "tqc"), ("memory", "crossq"), ("prioritised", "sac"),
        ("memory", "td3"), ("prioritised", "td3"), ("memory", "spg_p_multi"), ("prioritised", "spg_p_multi"), ("memory", "ppo_log"), ("recent", "ppo"))


# Implementations compared at equal settings: (ours, theirs), as (er, algo) cells.
PARITY = ((("memory", "sac_sb3"), ("default", "sb3_sac")),)


def parity_markdown(runs: list[Run]) -> str:
    """Per pair of ``PARITY`` present: ours - theirs, the mean paired by track with a 95% bootstrap
    interval over tracks; "within paired noise" when the interval holds 0 (no verdict on fewer than
    ``MIN_VERDICT_TRACKS`` tracks). '' if no pair is present."""
    lines = []
    for ours, theirs in PARITY:
        a, b = _finals(runs, *ours, None), _finals(runs, *theirs, None)
        if not a or not b:
            continue
        value, low, high, tracks = paired_bootstrap(a, b, _mean_difference)
        verdict = {None: "too few shared tracks to decide", 0: "within paired noise", 1: "ours higher",
                   -1: "ours lower"}[paired_sign(low, high, tracks)]
        shared = sorted(set(a) & set(b))
        per_track = ", ".join(f"{t}: {a[t] - b[t]:+.1f}" for t in shared)
        interval = f" [{low:+.1f}, {high:+.1f}]" if not math.isnan(low) else ""
        lines.append(f"| {markdown_cell(label(*ours))} | {markdown_cell(label(*theirs))} | {tracks} | {value:+.1f}{interval} | {verdict} | "
                     f"{per_track} |")
    if not lines:
        return ""
    return "\n".join(["### At equal settings", "",
                      "Final performance of two implementations configured alike, paired by track (ours - "
                      "theirs; 95% bootstrap interval over tracks).", "",
                      "| ours | theirs | tracks | mean difference | verdict | per track |",
                      "|---|---|---:|---|---|---|", *lines, ""])


def beyond_cell(er: str, algo: str) -> bool:
    """A cell of an algorithm or a replay mode the paper did not have (SAC, TD3, SB3's, prioritised)."""
    return algo not in ALGO_COLUMNS or er == "prioritised"


def is_beyond(run: Run) -> bool:
    """A run of a ``beyond_cell``."""
    return run.algo is not None and beyond_cell(run.er, run.algo)


def label(er: str, algo: str) -> str:
    return f"{ALGO_TITLES.get(algo, algo)}, {'both' if er == 'hybrid' else er}"


def _finals(runs: list[Run], er: str, algo: str, seeds: set[int] | None) -> dict[int, float]:
    return {r.seed: r.final_mean for r in runs
            if (r.er, r.algo) == (er, algo) and r.track_mode == "fixed" and r.status == "completed"
            and r.final_mean is not None and (seeds is None or r.seed in seeds)}


def _mean_se(values: list[float]) -> str:
    if not values:
        return ""
    mean = math.fsum(values) / len(values)
    if len(values) < 2:
        return f"{mean:.1f}"
    se = float(np.std(values, ddof=1)) / math.sqrt(len(values))
    return f"{mean:.1f} ± {se:.1f}"


def _track_sets(seeds: set[int]) -> list[tuple[str, set[int] | None]]:
    """The sections of a table: the paper's five tracks, then all of ``seeds`` (None: no
    filter) when they go beyond them."""
    sets: list[tuple[str, set[int] | None]] = [("the paper's five tracks", set(PAPER_SEEDS))]
    if seeds - set(PAPER_SEEDS):
        sets.append((f"all {len(seeds)} tracks", None))
    return sets


def in_section(cell_seeds: set[int], seeds: set[int] | None) -> bool:
    """Whether a cell with runs on ``cell_seeds`` (already those of the section) has a row in the
    section of ``seeds``: every section but all tracks (None), where only cells with runs beyond
    the paper's five tracks belong (a five-track mean would not compare with means over all)."""
    return seeds is not None or bool(cell_seeds - set(PAPER_SEEDS))


def _cells_present(runs: list[Run]) -> list[tuple[str, str]]:
    present = {(r.er, r.algo) for r in runs if r.track_mode == "fixed" and r.algo is not None}
    return [c for c in ROWS if c in present] + sorted(present - set(ROWS))


def beyond_rows(runs: list[Run], seeds: set[int] | None) -> list[dict]:
    reference = _finals(runs, *REFERENCE, seeds)
    rows = []
    for er, algo in _cells_present(runs):
        finals = _finals(runs, er, algo, seeds)
        if not finals or not in_section(set(finals), seeds):
            continue
        cell_runs = [r for r in runs if (r.er, r.algo) == (er, algo) and r.track_mode == "fixed"
                     and (seeds is None or r.seed in seeds)]
        scores = np.array(list(finals.values()))[:, None]
        point, low, high = stratified_bootstrap_ci(scores, iqm) if len(finals) > 1 else (iqm(scores), None, None)
        row = {"cell": label(er, algo), "er": er, "algo": algo, "runs": len(finals),
               "mean_se": _mean_se(list(finals.values())), "iqm": point, "iqm_low": low, "iqm_high": high,
               "collapsed": sum(v < COLLAPSE_BELOW for v in finals.values()),
               "diverged": sum(r.status == "diverged" for r in cell_runs)}
        row["is_reference"] = (er, algo) == REFERENCE
        if not row["is_reference"] and reference:
            value, lo, hi, tracks = paired_bootstrap(finals, reference, _mean_difference)
            row.update(diff=value, diff_low=lo, diff_high=hi, diff_tracks=tracks)
        timed = [r for r in cell_runs if (r.cpu_time, r.wall_time) != (None, None)]
        cpu = all(r.cpu_time is not None for r in timed)  # else wall time (runs made before CPU time was recorded)
        spent = [r.cpu_time if cpu else r.wall_time for r in timed]
        spent = [s for s in spent if s is not None]
        row["compute_s"], row["compute_is_cpu"] = (math.fsum(spent) / len(spent) if spent else None), cpu
        rows.append(row)
    return rows


def _diff_text(row: dict) -> str:
    if row["is_reference"]:
        return "(reference)"
    if "diff" not in row:
        return "(no reference runs)"
    if row["diff_tracks"] < 2 or math.isnan(row["diff_low"]):
        return f"{row['diff']:+.1f}"
    verdict = {None: "too few tracks to decide", 1: "higher", -1: "lower", 0: "undecided"}[
        paired_sign(row["diff_low"], row["diff_high"], row["diff_tracks"])]
    fewer = f" (on {row['diff_tracks']} tracks)" if row["diff_tracks"] < row["runs"] else ""  # the reference's
    return f"{row['diff']:+.1f} [{row['diff_low']:+.1f}, {row['diff_high']:+.1f}] {verdict}{fewer}"


def beyond_markdown(runs: list[Run]) -> str:
    """The beyond-the-paper table (see the module docstring), or '' if the sweep has no such cells."""
    if not any(is_beyond(r) for r in runs):
        return ""
    parts = ["Beyond the paper: final performance (mean total reward of the last 20 training episodes) per run, "
             f"on fixed tracks. IQM intervals resample runs (tracks); \"vs {label(*REFERENCE)}\" is the mean "
             "difference from the paper's best cell on the same tracks, with a 95% bootstrap interval over "
             f"tracks and a verdict from {MIN_VERDICT_TRACKS} tracks on. Compute per run: the CPU time of the "
             "process that trained it over the members it trained (every session of a resumed run); \"wall\" marks runs made before CPU time was recorded, for "
             "which it is the process's wall time over its members (the same when each process had a core).", ""]
    all_seeds = {r.seed for r in runs if r.track_mode == "fixed" and r.seed is not None}
    for title, seeds in _track_sets(all_seeds):
        rows = beyond_rows(runs, seeds)
        parts += [f"### On {title}", "",
                  f"| cell | runs | mean ± SE | IQM [95% CI] | vs {label(*REFERENCE)} | collapsed (final < "
                  f"{COLLAPSE_BELOW:g}) | diverged | compute per run |",
                  "|---|---:|---:|---|---|---:|---:|---:|"]
        for row in rows:
            ci = (f"{row['iqm']:.1f} [{row['iqm_low']:.1f}, {row['iqm_high']:.1f}]" if row["iqm_low"] is not None
                  else f"{row['iqm']:.1f}")
            spent = row["compute_s"]
            compute = "" if spent is None else f"{spent / 60:.1f} min" + ("" if row["compute_is_cpu"] else " wall")
            parts.append(f"| {markdown_cell(row['cell'])} | {row['runs']} | {row['mean_se']} | {ci} | {_diff_text(row)} | "
                         f"{row['collapsed']} | {row['diverged']} | {compute} |")
        parts.append("")
    parity = parity_markdown(runs)
    return "\n".join(parts + ([parity] if parity else []))


def generalisation_rows(runs: list[Run], seeds: set[int] | None = None) -> list[dict]:
    groups: dict[tuple[str, str, str], list[Run]] = {}
    for r in runs:
        if r.status == "completed" and r.evaluation and (seeds is None or r.seed in seeds):
            groups.setdefault((r.er, r.algo, r.track_mode), []).append(r)
    if seeds is None:  # all tracks: only the groups that have runs beyond the paper's tracks
        groups = {key: members for key, members in groups.items()
                  if any(r.seed not in PAPER_SEEDS for r in members)}
    order = {cell: i for i, cell in enumerate(ROWS)}
    rows = []
    for (er, algo, mode), members in sorted(groups.items(), key=lambda kv: (order.get(kv[0][:2], 99), kv[0])):
        own = [r.evaluation["own_track"] for r in members]
        unseen = [r.evaluation["mean"] for r in members]
        rows.append({"cell": label(er, algo), "train_tracks": mode, "runs": len(members),
                     "unseen_tracks": len(members[0].evaluation["tracks"]), "episodes": members[0].evaluation["episodes"],
                     "own": _mean_se(own), "unseen": _mean_se(unseen),
                     "gap": _mean_se([a - b for a, b in zip(own, unseen)])})
    return rows


def generalisation_markdown(runs: list[Run]) -> str:
    """The generalisation table on the paper's five tracks (where fixed- and random-track runs
    share their seeds, so the two modes compare on the same tracks), then, for the cells with
    evaluated runs beyond them, on all tracks; '' if no run was evaluated."""
    evaluated = {r.seed for r in runs if r.status == "completed" and r.evaluation and r.seed is not None}
    if not evaluated:
        return ""
    lines = ["Generalisation: the final deterministic policy of each run, evaluated on its own track (for "
             "random-track training, the track of its seed: one of its training tracks) and on unseen tracks "
             "(eval_seeds: never used in training); mean ± SE over runs. Gap = own - unseen, per run.", ""]
    for title, seeds in _track_sets(evaluated):
        rows = generalisation_rows(runs, seeds)
        if not rows:
            continue
        lines += [f"### Trained on {title}", "",
                  "| cell | training tracks | runs | own track | unseen tracks (mean) | gap |",
                  "|---|---|---:|---:|---:|---:|"]
        for row in rows:
            lines.append(f"| {markdown_cell(row['cell'])} | {row['train_tracks']} | {row['runs']} | {row['own']} | "
                         f"{row['unseen']} ({row['unseen_tracks']} tracks x {row['episodes']} episodes) | {row['gap']} |")
        lines.append("")
    return "\n".join(lines)
