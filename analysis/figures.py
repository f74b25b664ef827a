"""The report's figures: learning curves, the IQM view, the paper tracks, an agent frame.

Needs the ``render`` extra (matplotlib; pygame for the agent frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from analysis.aggregate import stratified_bootstrap_ci
from analysis.report import ALGO_COLUMNS, COLUMN_TITLES, ER_ROWS, Run
from engine.names import figure_label
from racing.figures import import_pyplot, save_figure, tracks_figure


def curves(runs: list[Run], algo: str, er: str) -> np.ndarray | None:
    """[seeds, episodes] learning curves of the completed runs of one cell (common length)."""
    rows = [r.rewards for r in runs if (r.algo, r.er) == (algo, er) and r.status == "completed" and r.rewards]
    if not rows:
        return None
    length = min(len(r) for r in rows)
    return np.array([r[:length] for r in rows])


def _plot_band(ax, data: np.ndarray, label: str) -> None:
    mean = data.mean(axis=0)
    sem = data.std(axis=0, ddof=1) / np.sqrt(len(data)) if len(data) > 1 else np.zeros_like(mean)
    x = np.arange(len(mean))
    ax.plot(x, mean, label=figure_label(f"{label} (n={len(data)})"), linewidth=1.2)
    ax.fill_between(x, mean - sem, mean + sem, alpha=0.25)


def learning_curve_figures(runs: list[Run], out: Path) -> list[Path]:
    """One figure per algorithm (a line per replay mode) and per replay mode (a line per
    algorithm): mean total reward per episode over seeds, with a ±1 standard-error band."""
    plt = import_pyplot()
    written = []
    groups = [(f"curves_{a}.png", COLUMN_TITLES[a], [(a, er, er) for er in ER_ROWS]) for a in ALGO_COLUMNS]
    groups += [(f"curves_er-{er}.png", f"replay: {er}", [(a, er, COLUMN_TITLES[a]) for a in ALGO_COLUMNS])
               for er in ER_ROWS]
    for name, title, members in groups:
        series = [(label, curves(runs, a, er)) for a, er, label in members]
        series = [(label, data) for label, data in series if data is not None]
        if not series:
            continue
        fig, ax = plt.subplots(figsize=(7, 4))
        for label, data in series:
            _plot_band(ax, data, label)
        ax.set(title=title, xlabel="episode", ylabel="total reward (mean over tracks, ±1 SE)")
        ax.axhline(0, color="grey", linewidth=0.5)
        ax.legend(loc="lower right", fontsize=8)
        save_figure(fig, out / name, dpi=110)
        written.append(out / name)
    return written


def frontier_series(runs: list[Run], oracle: dict[int, float], smooth: int = 10) -> list[tuple[str, list, float | None]]:
    """The data of ``frontier_figure``: per track set (the paper's five tracks, then all tracks when
    the runs go beyond them, with the cells that do), its title, one (label, environment steps,
    mean, SE) per cell and the oracle's mean over the cells' tracks (None unless it scored them
    all); [] if no run is beyond the paper. A cell's value at a step is the mean over tracks of
    the total reward per episode, averaged over the last ``smooth`` episodes up to that step."""
    from analysis.beyond import REFERENCE, _cells_present, _track_sets, beyond_cell, in_section, is_beyond, label

    finished = [r for r in runs if r.status == "completed" and r.track_mode == "fixed" and r.rewards]
    if not any(is_beyond(r) for r in finished):
        return []
    cells = [REFERENCE] + [c for c in _cells_present(finished) if c != REFERENCE and beyond_cell(*c)]
    panels = []
    for title, seeds in _track_sets({r.seed for r in finished}):
        lines, tracks = [], set()
        for er, algo in cells:
            mine = [r for r in finished if (r.er, r.algo) == (er, algo) and (seeds is None or r.seed in seeds)]
            if not mine or not in_section({r.seed for r in mine}, seeds):
                continue
            tracks |= {r.seed for r in mine}
            length = min(len(r.rewards) for r in mine)
            width = min(smooth, length)
            data = np.array([np.convolve(r.rewards[:length], np.ones(width) / width, mode="valid") for r in mine])
            steps = mine[0].episode_steps * (np.arange(data.shape[1]) + width)
            sem = data.std(axis=0, ddof=1) / np.sqrt(len(data)) if len(data) > 1 else np.zeros(data.shape[1])
            lines.append((f"{label(er, algo)} (n={len(data)})", steps, data.mean(axis=0), sem))
        ceiling = float(np.mean([oracle[t] for t in sorted(tracks)])) if tracks and tracks <= set(oracle) else None
        panels.append((title, lines, ceiling))
    return panels


def _cell_of(label: str) -> str:
    """A frontier line's cell: its label without the run count ("SAC, memory (n=5)")."""
    return label.rsplit(" (n=", 1)[0]


def cell_colours(panels) -> dict[str, tuple]:
    """One colour per cell across all panels (a cell keeps its colour from panel to panel), in
    order of first appearance: tab20's ten dark colours (tab10's hues), then its ten light ones
    (the default cycle would repeat a colour from the 11th line on)."""
    from matplotlib import colormaps

    cells = list(dict.fromkeys(_cell_of(label) for _, lines, _ in panels for label, *_ in lines))
    palette = colormaps["tab20"].colors
    order = [*range(0, 20, 2), *range(1, 20, 2)]
    return {cell: palette[order[i % 20]] for i, cell in enumerate(cells)}


def frontier_figure(runs: list[Run], oracle: dict[int, float], path: Path, smooth: int = 10) -> Path | None:
    """Every method against environment steps (``frontier_series``): the paper's best cell, the
    cells beyond the paper (SAC, TD3, prioritised replay, Stable-Baselines3) with ±1 SE bands over
    tracks, and the oracle as a dashed line. None if no run is beyond the paper."""
    panels = frontier_series(runs, oracle, smooth)
    if not panels:
        return None
    plt = import_pyplot()
    colours = cell_colours(panels)
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 4.5), squeeze=False)
    for ax, (title, lines, ceiling) in zip(axes[0], panels):
        for label, steps, mean, sem in lines:
            colour = colours[_cell_of(label)]
            ax.plot(steps, mean, label=figure_label(label), linewidth=1.2, color=colour)
            ax.fill_between(steps, mean - sem, mean + sem, alpha=0.2, color=colour)
        if ceiling is not None:
            ax.axhline(ceiling, color="black", linestyle="--", linewidth=1, label=f"oracle ({ceiling:.1f})")
        ax.axhline(0, color="grey", linewidth=0.5)
        ax.set(title=f"On {title}", xlabel="environment steps",
               ylabel=f"total reward per episode (last {smooth}; mean over tracks ±1 SE)")
        ax.legend(loc="lower right", fontsize=7)
    return save_figure(fig, path, dpi=110)


def iqm_rows(runs: list[Run], reps: int = 2000) -> list[tuple[str, float, float, float, int]]:
    """(cell, IQM, low, high, runs) per cell: each completed run's final performance is one
    score, and the 95% interval comes from resampling runs (tracks), as rliable does: it is
    run-to-run uncertainty, not one run's episode noise."""
    rows = []
    for er in ER_ROWS:
        for algo in ALGO_COLUMNS:
            done = [r for r in runs
                    if (r.er, r.algo) == (er, algo) and r.status == "completed" and r.final_mean is not None]
            if not done:
                continue
            point, low, high = stratified_bootstrap_ci(np.array([r.final_mean for r in done])[:, None], reps=reps)
            budgets = sorted({r.budget for r in done if r.budget is not None})
            mixed = f" (mixed budgets: {', '.join(map(str, budgets))} episodes)" if len(budgets) > 1 else ""
            rows.append((f"{er} / {COLUMN_TITLES[algo]}{mixed}", point, low, high, len(done)))
    return rows


def iqm_figure(rows: list[tuple[str, float, float, float, int]], path: Path) -> Path | None:
    if not rows:
        return None
    plt = import_pyplot()
    fig, ax = plt.subplots(figsize=(7, 0.35 * len(rows) + 1.2))
    y = np.arange(len(rows))[::-1]
    for yi, (label, point, low, high, _) in zip(y, rows):
        ax.plot([low, high], [yi, yi], color="tab:blue", linewidth=3, alpha=0.5)
        ax.plot(point, yi, "o", color="tab:blue")
    ax.set_yticks(y, [figure_label(r[0]) for r in rows], fontsize=8)
    ax.set(xlabel="IQM of the runs' final performance (95% bootstrap CI over runs)")
    return save_figure(fig, path, dpi=110)


def paper_tracks_figure(path: Path) -> Path:
    tracks_figure(path)
    return path


def agent_frame(run_dir: Path, path: Path, step: int = 120) -> Path:
    """Frame ``step`` of one episode of the run's deterministic policy on its own track."""
    import imageio.v3 as imageio

    from engine.evaluation import load_policy, make_env, run_episode
    from door import files

    net, settings = load_policy(run_dir)
    env = make_env(settings, settings["seed"], render_mode="rgb_array")
    frames: list = []
    run_episode(net, env, seed=0, frames=frames)
    env.close()
    files.write_atomic(path, imageio.imwrite("<bytes>", frames[min(step, len(frames) - 1)], extension=Path(path).suffix))
    return path
