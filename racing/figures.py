"""Figures of tracks with matplotlib (the ``render`` extra: ``racing.render.RENDER_EXTRA``)."""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from racing.config import PAPER_TRACK_SEEDS, RacingConfig
from racing.track import Track, track_from_seed


def import_pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the installation
        from racing.render import RENDER_EXTRA

        raise ImportError(f"figures need matplotlib, in the render extra: {RENDER_EXTRA}") from exc
    return plt


def draw_track(ax, track: Track, trail: np.ndarray | None = None) -> None:
    """Fill the track's checkpoints, outline its walls, mark start and finish."""
    for i in range(track.num_checkpoints):
        ax.fill(*track.checkpoint(i).T, color="0.55", linewidth=0)
    for wall in (track.left_wall, track.right_wall):
        ax.plot(*wall.T, color="black", linewidth=0.8)
    ax.plot(*np.stack([track.left_wall[0], track.right_wall[0]]).T, color="tab:green", linewidth=2)
    if not track.closed:  # a circuit's finish is its start line
        ax.plot(*np.stack([track.left_wall[-1], track.right_wall[-1]]).T, color="tab:red", linewidth=2)
    if trail is not None and len(trail):
        ax.plot(*np.asarray(trail).T, color="tab:blue", linewidth=1)
    ax.set_aspect("equal")
    ax.axis("off")


def tracks_figure(path: str | Path, seeds: Sequence[int] = PAPER_TRACK_SEEDS,
                  config: RacingConfig = RacingConfig(), width: float = 14.0) -> Path:
    """One panel per track seed, side by side, each as wide as its track (the paper's Figure 1)."""
    plt = import_pyplot()
    tracks = [track_from_seed(s, config) for s in seeds]
    spans = [np.subtract(*reversed(t.bounds())) for t in tracks]
    widths = [max(w / h, 0.2) for w, h in spans]
    height = min(max(width / sum(widths), 2.0), 6.0) + 0.5  # and the legend
    fig, axes = plt.subplots(1, len(tracks), figsize=(width, height),
                             gridspec_kw={"width_ratios": widths}, squeeze=False)
    for ax, track, seed in zip(axes[0], tracks, seeds):
        draw_track(ax, track)
        ax.set_title(str(seed), fontsize=9)
    from matplotlib.lines import Line2D

    marks = [Line2D([], [], color="tab:green", linewidth=2, label="start line"),
             Line2D([], [], color="tab:red", linewidth=2, label="finish line (the episode ends there)"),
             Line2D([], [], color="0.55", linewidth=6, label="the road: one grey checkpoint after another")]
    fig.legend(handles=marks, loc="lower center", ncol=3, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.14, 1, 0.9))  # room for the titles above and the legend below
    return save_figure(fig, path, dpi=120, tight=False)


def track_file_figure(track: Track, path: str | Path, title: str | None = None,
                      crossing: Sequence[tuple[np.ndarray, np.ndarray]] = ()) -> Path:
    """One track (e.g. a file's): its name above a description (``title``), every tenth checkpoint
    numbered (about forty on a long circuit), the start line and an arrow for the direction of travel;
    ``crossing``: wall segments ``(from, to)`` drawn in red (where a refused file's walls cross)."""
    plt = import_pyplot()
    low, high = track.bounds()
    span = np.maximum(high - low, 1.0)
    width = min(max(6.0 * span[0] / span[1], 4.0), 12.0)
    fig, ax = plt.subplots(figsize=(width, 6.0))
    draw_track(ax, track)
    every = max(10, round(track.num_checkpoints / 40, -1))  # about 40 numbers on a long circuit, not 120 overlapping
    for i in range(0, track.num_checkpoints, int(every)):
        ax.annotate(str(i), track.centres[i], fontsize=6, ha="center", va="center", color="black",
                    bbox={"boxstyle": "round,pad=0.15", "facecolor": "white", "edgecolor": "none", "alpha": 0.8})
    ahead = track.centres[min(max(1, track.num_checkpoints // 25), track.num_checkpoints - 1)]  # a 25th of the way
    if track.num_checkpoints > 1:  # the direction of travel, from the start
        ax.annotate("", xy=ahead, xytext=track.centres[0],
                    arrowprops={"arrowstyle": "-|>", "color": "tab:green", "linewidth": 1.5})
    for start, end in crossing:
        ax.plot(*np.stack([start, end]).T, color="red", linewidth=2.5)
        ax.plot(*((np.asarray(start) + np.asarray(end)) / 2), "o", markersize=12, markerfacecolor="none",
                markeredgecolor="red")
    name = track.name or "track"
    detail = title if title and title != name else ""
    if detail.startswith(f"{name}: "):  # tracks.py's description names the track first
        detail = detail[len(name) + 2:]
    ax.set_title("\n".join([name, *textwrap.wrap(detail, max(int(width * 11), 40))]), fontsize=9)
    return _save(plt, fig, path)


def _save(plt, fig, path: str | Path) -> Path:
    return save_figure(fig, path, dpi=120)


def save_figure(fig, path: str | Path, dpi: int = 120, tight: bool = True) -> Path:
    """Draw ``fig`` into memory (its format from the suffix), close it, and write it whole through
    the file door (``door.files.write_atomic``; its folder made if missing)."""
    import io

    from door import files

    plt = import_pyplot()
    if tight:  # (a figure that laid itself out says so)
        fig.tight_layout()
    path = Path(path)
    buffer = io.BytesIO()
    fig.savefig(buffer, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    files.folder(path.parent, path.parent, create=True)
    files.write_atomic(path, buffer.getvalue())
    return path
