"""A sweep's cells as rliable reports them (``analysis.aggregate``): ``statistics.md``, ``profiles.png`` and
``improvement.png`` in a report.

Each cell's completed runs on fixed tracks are its scores, on the oracle's scale of each run's track
where the oracle scored every one of them (else in total reward), one task of many runs (a run here is
one track; the cells of Table 1 have one run per track): the IQM, mean and optimality gap with
95% stratified bootstrap intervals over runs; the performance profile (the fraction of runs above each
score); and the probability of improvement for the pairs of cells the paper's conclusions compare,
with its interval. These answer unpaired questions ("how good is this cell", "how often does a run
of one beat a run of the other"); the paired-by-track effects of ``conclusions.md`` stay where the
question is paired.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from analysis import aggregate
from analysis.report import ALGO_COLUMNS, COLUMN_TITLES, ER_ROWS, Run, normalised
from engine.names import figure_label, markdown_cell

PRIORITISED = {"spg": "spg_p", "spg_multi": "spg_p_multi"}  # SPG and its prioritised twin (the paper's SPG-p)


def cell_scores(runs: list[Run], oracle: dict[int, float]) -> tuple[dict[tuple[str, str], np.ndarray], bool]:
    """({(er, algo): scores [runs, 1]}, on the oracle's scale): the completed fixed-track runs of each cell."""
    done = [r for r in runs if r.status == "completed" and r.final_mean is not None and r.track_mode == "fixed"]
    scaled = bool(done) and all(normalised(r, oracle) is not None for r in done)
    cells: dict[tuple[str, str], list[float]] = {}
    for r in done:
        cells.setdefault((r.er, r.algo), []).append(normalised(r, oracle) if scaled else r.final_mean)
    return {key: np.array(values)[:, None] for key, values in cells.items()}, scaled


def title(key: tuple[str, str]) -> str:
    er, algo = key
    return f"{COLUMN_TITLES.get(algo, algo)}, {er}"


def _ordered(cells: dict) -> list[tuple[str, str]]:
    known = [(er, algo) for er in ER_ROWS for algo in ALGO_COLUMNS if (er, algo) in cells]
    return known + sorted(set(cells) - set(known))


def comparisons(cells: dict) -> list[tuple[tuple[str, str], tuple[str, str], str]]:
    """(X, Y, why) for the pairs the paper's conclusions compare, where the sweep has both cells."""
    pairs = [(("recent", "ppo"), ("recent", algo), "PPO against SPG, recent experience")
             for algo in ("spg", "spg_multi", "spg_p", "spg_p_multi")]
    pairs += [((er, algo), ("recent", "ppo"), "SPG with replay against the best PPO cell")
              for er in ("memory", "hybrid") for algo in ("spg", "spg_multi", "spg_p", "spg_p_multi")]
    pairs += [((er, prioritised), (er, plain), "prioritised against plain SPG")
              for er in ER_ROWS for plain, prioritised in PRIORITISED.items()]
    return [(x, y, why) for x, y, why in pairs if x in cells and y in cells]


def statistics_markdown(runs: list[Run], oracle: dict[int, float], reps: int = aggregate.REPS) -> str:
    """The aggregate metrics and the probabilities of improvement, as Markdown ("" without completed runs)."""
    cells, scaled = cell_scores(runs, oracle)
    if not cells:
        return ""
    scale = "the oracle's scale of each run's track (0: a car that stands still, 1: the oracle)" if scaled \
        else "total reward (the oracle has not scored every track)"
    metrics = ("IQM", "mean") + (("optimality gap",) if scaled else ())  # (rliable's median is over tasks: one here)
    lines = [f"Aggregate metrics as rliable computes them, on {scale}; each cell's runs (one per track) resampled "
             f"with replacement, {reps:,} times (stratified bootstrap), 95% percentile intervals. The optimality "
             "gap is how far below the oracle the runs fall on average.", "",
             "| cell | runs | " + " | ".join(metrics) + " |", "|---|---:|" + "---|" * len(metrics)]
    digits = 3 if scaled else 1
    for key in _ordered(cells):
        scores = cells[key]
        row = []
        for name in metrics:
            point, low, high = aggregate.stratified_bootstrap_ci(scores, aggregate.ESTIMATORS[name], reps=reps)
            row.append(f"{point:.{digits}f} [{low:.{digits}f}, {high:.{digits}f}]" if len(scores) > 1
                       else f"{point:.{digits}f} (n/a: one run)")
        lines.append(f"| {markdown_cell(title(key))} | {len(scores)} | " + " | ".join(row) + " |")
    pairs = comparisons(cells)
    if pairs:
        lines += ["", f"Probability of improvement P(X > Y): the chance that a run of X scores above a run of Y (ties "
                  f"count half), with its 95% interval (X's and Y's runs resampled independently, {reps:,} times). "
                  "Above 0.5 with the interval above 0.5: X tends to beat Y.", "",
                  "| X | Y | compares | P(X > Y) [95% CI] |", "|---|---|---|---|"]
        for x, y, why in pairs:
            point, low, high = aggregate.probability_of_improvement_ci(cells[x], cells[y], reps=reps)
            lines.append(f"| {markdown_cell(title(x))} | {markdown_cell(title(y))} | {why} | {point:.2f} [{low:.2f}, {high:.2f}] |")
    return "\n".join(lines) + "\n"


def statistics_figures(runs: list[Run], oracle: dict[int, float], out: Path,
                       reps: int = aggregate.REPS) -> list[Path]:
    """``profiles.png`` (each replay mode's cells' performance profiles, with bands) and ``improvement.png``
    (the probabilities of improvement with their intervals)."""
    from racing.figures import import_pyplot, save_figure

    cells, scaled = cell_scores(runs, oracle)
    if not cells:
        return []
    plt = import_pyplot()
    modes = [er for er in ER_ROWS if any(key[0] == er for key in cells)] or sorted({key[0] for key in cells})
    everything = np.concatenate(list(cells.values())).ravel()
    taus = np.linspace(min(0.0, everything.min()), max(1.0 if scaled else 0.0, everything.max()) * 1.02, 101)
    fig, axes = plt.subplots(1, len(modes), figsize=(4.2 * len(modes), 3.4), squeeze=False, sharey=True)
    for ax, er in zip(axes[0], modes):
        mine = {COLUMN_TITLES.get(k[1], k[1]): cells[k] for k in _ordered(cells) if k[0] == er}
        styles = line_styles(sorted(mine, key=lambda name: -aggregate.iqm(mine[name])))
        for name, style in styles.items():
            profile, low, high = aggregate.performance_profile(mine[name], taus)
            _profile_line(ax, taus, profile, low, high, style, band_alpha=0.15)
        ax.set(title=f"{er}", xlabel="oracle-normalised final performance" if scaled else "final performance")
        ax.legend(fontsize=7, loc="lower left")
    axes[0][0].set(ylabel="fraction of runs above")
    written = [save_figure(fig, out / "profiles.png", dpi=110)]
    pairs = comparisons(cells)
    if pairs:
        fig, ax = plt.subplots(figsize=(7, 0.33 * len(pairs) + 1.2))
        y = np.arange(len(pairs))[::-1]
        for yi, (a, b, _) in zip(y, pairs):
            point, low, high = aggregate.probability_of_improvement_ci(cells[a], cells[b], reps=reps)
            ax.plot([low, high], [yi, yi], color="tab:blue", linewidth=3, alpha=0.5)
            ax.plot(point, yi, "o", color="tab:blue")
        ax.axvline(0.5, color="0.5", linewidth=0.8, linestyle="--")
        ax.set_yticks(y, [figure_label(f"{title(a)} > {title(b)}") for a, b, _ in pairs], fontsize=7)
        ax.set(xlim=(0, 1), xlabel="P(X > Y): probability of improvement (95% interval)")
        written.append(save_figure(fig, out / "improvement.png", dpi=110))
    return written


def board_statistics(cells: dict[str, np.ndarray], reference: str | None,
                     reps: int = aggregate.REPS) -> str:
    """The leaderboard's agents as rliable reports them: ``cells`` {agent: oracle-normalised scores [runs,
    tracks]} (the tracks are the tasks; each track's runs resampled), the IQM, mean and optimality gap with
    95% intervals, and each agent's probability of improvement over ``reference`` (an agent's name)."""
    metrics = ("IQM", "mean", "optimality gap")
    lines = [f"The benchmark's agents as rliable reports them, on the oracle's scale of each track: each "
             f"agent's runs on each of the ten tracks, the tracks as tasks, runs resampled within each track "
             f"({reps:,} times, stratified bootstrap), 95% percentile intervals; agents of one run (the reference "
             "drivers) have none. P(X > ref): the chance that a run of the agent beats a run of "
             f"{markdown_cell(reference) if reference else 'the reference'} on a track, averaged over tracks.", "",
             "| agent | runs | " + " | ".join(metrics) + (" | P(X > ref) [95% CI] |" if reference else " |"),
             "|---|---:|" + "---|" * (len(metrics) + bool(reference))]
    order = sorted(cells, key=lambda name: -aggregate.iqm(cells[name]))
    for name in order:
        scores = cells[name]
        row = []
        for metric in metrics:
            point, low, high = aggregate.stratified_bootstrap_ci(scores, aggregate.ESTIMATORS[metric], reps=reps)
            row.append(f"{point:.3f} [{low:.3f}, {high:.3f}]" if len(scores) > 1 else f"{point:.3f}")
        if reference:
            if name == reference:
                row.append("(ref)")
            else:
                point, low, high = aggregate.probability_of_improvement_ci(scores, cells[reference], reps=reps)
                row.append(f"{point:.2f} [{low:.2f}, {high:.2f}]")
        lines.append(f"| {markdown_cell(name)} | {len(scores)} | " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def board_profiles(cells: dict[str, np.ndarray], path: Path) -> Path:
    """Performance profiles of the leaderboard's agents (the fraction of run-track scores above each
    oracle-normalised score), learned agents with bands, reference drivers dashed."""
    from racing.figures import import_pyplot, save_figure

    plt = import_pyplot()
    taus = np.linspace(0.0, 1.05, 106)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ranked = sorted(cells, key=lambda n: -aggregate.iqm(cells[n]))
    for name, style in line_styles(ranked, lambda n: n.startswith("reference:")).items():
        profile, low, high = aggregate.performance_profile(cells[name], taus)
        _profile_line(ax, taus, profile, low, high, style, band_alpha=0.1)
    ax.set(xlabel="oracle-normalised score on a benchmark track", ylabel="fraction of runs x tracks above",
           xlim=(0.4, 1.05))
    ax.legend(fontsize=6, loc="lower left")
    return save_figure(fig, path, dpi=110)


COLOURED = 6  # the learned agents a figure draws in colours of their own; more would share colours


def line_styles(ranked: list[str], is_reference=lambda name: False) -> dict[str, dict]:
    """Each line's style in a figure of agents ``ranked`` best first, so that a reader can tell every
    coloured line apart: the reference drivers dashed in dark tones, the best ``COLOURED`` other agents
    each in a colour of its own with its band, the rest thin grey without bands under one legend entry.
    The legend follows the returned order; the grey lines are drawn beneath (zorder)."""
    references = [n for n in ranked if is_reference(n)]
    learned = [n for n in ranked if not is_reference(n)]
    palette = ["tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]
    darks = ["black", "0.35", "tab:olive", "tab:cyan"]
    rest = learned[COLOURED:]
    styles = {name: {"color": palette[i], "linewidth": 1.3, "band": True, "zorder": 3, "label": name}
              for i, name in enumerate(learned[:COLOURED])}
    styles.update({name: {"color": darks[i % len(darks)], "linewidth": 1.2, "band": False, "zorder": 2,
                          "linestyle": "--", "label": name} for i, name in enumerate(references)})
    styles.update({name: {"color": "0.72", "linewidth": 0.8, "band": False, "zorder": 1,
                          "label": f"{len(rest)} other agents" if i == 0 else None} for i, name in enumerate(rest)})
    return styles


def _profile_line(ax, taus, profile, low, high, style: dict, band_alpha: float) -> None:
    label = style.get("label")
    ax.plot(taus, profile, color=style["color"], linewidth=style["linewidth"], zorder=style["zorder"],
            linestyle=style.get("linestyle", "-"), label=None if label is None else figure_label(label))
    if style["band"]:
        ax.fill_between(taus, low, high, color=style["color"], alpha=band_alpha, linewidth=0, zorder=style["zorder"])
