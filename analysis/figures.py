"""The report's figures: learning curves, the IQM view, the paper tracks, an agent frame.

Needs the ``render`` extra (matplotlib; pygame for the agent frame).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from analysis.aggregate import stratified_bootstrap_ci
from analysis.report import ALGO_COLUMNS, COLUMN_TITLES, ER_ROWS, Run
from racing.figures import import_pyplot, tracks_figure


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
    ax.plot(x, mean, label=f"{label} (n={len(data)})", linewidth=1.2)
    ax.fill_between(x, mean - sem, mean + sem, alpha=0.25)


def learning_curve_figures(runs: list[Run], out: Path) -> list[Path]:
    """One figure per algorithm (a line per replay mode) and per replay mode (a line per
    algorithm): mean total reward per episode over seeds, with a ±1 standard-error band."""
    plt = import_pyplot()
    written = []
    groups = [(f"curves_{a}.png", COLUMN_TITLES[a], [(a, er, er) for er in ER_ROWS]) for a in ALGO_COLUMNS]
    groups += [(f"curves_er-{er}.png", f"replay: {er}", [(a, er, COLUMN_TITLES[a]) for a in ALGO_COLUMNS])
               for er in ER_ROWS]
    from analysis.beyond import ROWS, is_beyond, label

    if any(is_beyond(r) for r in runs):
        groups.append(("curves_beyond.png", "beyond the paper", [(a, er, label(er, a)) for er, a in ROWS]))
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
        fig.tight_layout()
        fig.savefig(out / name, dpi=110)
        plt.close(fig)
        written.append(out / name)
    return written


def iqm_rows(runs: list[Run], reps: int = 2000) -> list[tuple[str, float, float, float, int]]:
    """(cell, IQM, low, high, runs) per cell: each completed run's final performance is one
    score, and the 95% interval comes from resampling runs (tracks), as rliable does: it is
    run-to-run uncertainty, not one run's episode noise."""
    rows = []
    for er in ER_ROWS:
        for algo in ALGO_COLUMNS:
            finals = [r.final_mean for r in runs
                      if (r.er, r.algo) == (er, algo) and r.status == "completed" and r.final_mean is not None]
            if not finals:
                continue
            point, low, high = stratified_bootstrap_ci(np.array(finals)[:, None], reps=reps)
            rows.append((f"{er} / {COLUMN_TITLES[algo]}", point, low, high, len(finals)))
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
    ax.set_yticks(y, [r[0] for r in rows], fontsize=8)
    ax.set(xlabel="IQM of the runs' final performance (95% bootstrap CI over runs)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def paper_tracks_figure(path: Path) -> Path:
    tracks_figure(path)
    return path


def agent_frame(run_dir: Path, path: Path, step: int = 120) -> Path:
    """Frame ``step`` of one episode of the run's deterministic policy on its own track."""
    import imageio.v2 as imageio

    from engine.evaluation import load_policy, make_env, run_episode

    net, settings = load_policy(run_dir)
    env = make_env(settings, settings["seed"], render_mode="rgb_array")
    frames: list = []
    run_episode(net, env, seed=0, frames=frames)
    env.close()
    imageio.imwrite(path, frames[min(step, len(frames) - 1)])
    return path
