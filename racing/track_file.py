"""Tracks from files: a centre line with the track's width to each side, in CSV.

The columns are those of the TUM racetrack-database (``x_m, y_m, w_tr_right_m, w_tr_left_m``):
one row per centre-line point, its coordinates and the distance from it to the right and to
the left wall. Lines starting with ``#`` are comments; two of them may say how to read the file:

    # closed: true      (a circuit: the last point joins the first; default false)
    # scale: 16.0       (simulator units, pixels, per file unit; default 1)
    # x_m,y_m,w_tr_right_m,w_tr_left_m
    0.0,-10.0,100.0,100.0
    ...

A header row of the column names (with or without ``#``) is optional. ``load_track`` arguments
override the comments (a TUM file is a circuit in metres: ``closed=True, scale=...``).

How a file becomes walls: the walls at a point lie on the line through it perpendicular to the
segment that arrives at it (the first point of an open track: the segment that leaves it), at
the given distances; checkpoint ``i`` is the quadrilateral between points ``i`` and ``i + 1``
(a circuit's last joins its last point to its first). The track is then placed as the
generated tracks are: its first point at ``(0, start_line_y)`` and its start heading along
+y, so the car starts ``-start_line_y`` pixels past the start line. A generated track exported
with ``save_track`` and loaded again has the same walls from its third point on (to 1e-12 of
the wall lengths), its first two points as this rule places them, all turned and moved to this
pose: a file track is a track of its own, and its scores are not the seed's.

A bad file is refused whole with one ``TrackFileError`` naming the line and the problem:
missing or extra columns, values that are not finite numbers, widths not above zero, fewer
than three points, a point repeating the one before it, or walls that cross themselves (or
each other).
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from racing.config import RacingConfig
from racing.track import Track

COLUMNS = ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m")
EXAMPLES = Path(__file__).resolve().parent / "tracks"  # the example files that ship with the package


class TrackFileError(ValueError):
    """A track file that cannot be loaded; the message names the line and the problem."""


def example(name: str) -> Path:
    """The path of an example track file shipped with the package (``racing/tracks/<name>.csv``)."""
    path = EXAMPLES / f"{name}.csv"
    if not path.is_file():
        names = sorted(p.stem for p in EXAMPLES.glob("*.csv"))
        raise TrackFileError(f"no example track {name!r}; the examples are {names}")
    return path


MAX_ROWS = 5_000  # points of a track file (real circuits: about 1,000); the ray tables grow with their square
MAX_BYTES = 4 * 1024 * 1024  # the file's size, checked before it is read


def read_rows(path: Path) -> tuple[np.ndarray, list[int], dict]:
    """The file's points (M, 4), the line number of each, and its ``# key: value`` settings; at
    most ``MAX_ROWS`` points in a file of at most ``MAX_BYTES`` (a UTF-8 byte-order mark is allowed)."""
    path = Path(path)
    try:
        if not path.is_file():  # a device (/dev/zero) or a pipe would be read without end
            raise TrackFileError(f"{path}: cannot be read (not a regular file: a device, a pipe or a folder)"
                                 if path.exists() else f"{path}: cannot be read (no such file)")
        with open(path, "rb") as f:
            data = f.read(MAX_BYTES + 1)
        if len(data) > MAX_BYTES:
            raise TrackFileError(f"{path}: more than {MAX_BYTES:,} bytes, more than a track file holds (at most "
                                 f"{MAX_ROWS:,} points)")
        text = data.decode("utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise TrackFileError(f"{path}: cannot be read ({type(err).__name__}: {err})") from None
    rows, lines, settings = [], [], {}
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            body = stripped.lstrip("#").strip()
            if ":" in body and body.split(":", 1)[0].strip() in ("closed", "scale"):
                key, value = (part.strip() for part in body.split(":", 1))
                settings[key] = _setting(path, number, key, value)
            continue
        cells = next(csv.reader([stripped]))
        if [c.strip() for c in cells] == list(COLUMNS):
            continue  # a header row without '#'
        if len(cells) != len(COLUMNS):
            raise TrackFileError(f"{path}, line {number}: expected {len(COLUMNS)} values ({', '.join(COLUMNS)}), "
                                 f"got {len(cells)}")
        values = []
        for name, cell in zip(COLUMNS, cells):
            try:
                value = float(cell)
            except ValueError:
                raise TrackFileError(f"{path}, line {number}: {name} is {cell.strip()!r}, not a number") from None
            if not math.isfinite(value):
                raise TrackFileError(f"{path}, line {number}: {name} is {cell.strip()}, not a finite number")
            values.append(value)
        for name, value in zip(COLUMNS[2:], values[2:]):
            if value <= 0:
                raise TrackFileError(f"{path}, line {number}: {name} must be > 0 (a width), got {value:g}")
        rows.append(values)
        lines.append(number)
        if len(rows) > MAX_ROWS:
            raise TrackFileError(f"{path}, line {number}: more than {MAX_ROWS:,} points, more than a track file holds "
                                 "(resample the centre line more coarsely)")
    return np.array(rows, dtype=np.float64).reshape(-1, 4), lines, settings


def _setting(path: Path, number: int, key: str, value: str):
    if key == "closed":
        if value.lower() not in ("true", "false"):
            raise TrackFileError(f"{path}, line {number}: closed must be true or false, got {value!r}")
        return value.lower() == "true"
    try:
        scale = float(value)
    except ValueError:
        scale = float("nan")
    if not (math.isfinite(scale) and scale > 0):
        raise TrackFileError(f"{path}, line {number}: scale must be a number > 0, got {value!r}")
    return scale


def load_track(path: Path | str, scale: float | None = None, closed: bool | None = None,
               config: RacingConfig = RacingConfig()) -> Track:
    """The track of a file (see the module docstring); ``TrackFileError`` if it is not one."""
    path = Path(path)
    points, lines, settings = read_rows(path)
    closed = settings.get("closed", False) if closed is None else bool(closed)
    scale = settings.get("scale", 1.0) if scale is None else scale
    if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise TrackFileError(f"{path}: scale must be a number > 0, got {scale!r}")
    if closed and len(points) > 3 and np.array_equal(points[0, :2], points[-1, :2]):
        points, lines = points[:-1], lines[:-1]  # a circuit written with its first point repeated at the end
    if len(points) < 3:
        raise TrackFileError(f"{path}: {len(points)} point(s); a track needs at least 3 (2 checkpoints)")
    xy, right, left = points[:, :2] * scale, points[:, 2] * scale, points[:, 3] * scale
    steps = np.diff(np.vstack([xy, xy[:1]]) if closed else xy, axis=0)
    lengths = np.hypot(steps[:, 0], steps[:, 1])
    if (lengths == 0).any():
        i = int(np.flatnonzero(lengths == 0)[0])
        after = lines[(i + 1) % len(lines)]
        raise TrackFileError(f"{path}, line {after}: repeats the point of line {lines[i]}")
    arriving = np.vstack([steps[-1:], steps[:-1]]) if closed else np.vstack([steps[:1], steps])  # (M, 2)
    tangent = arriving / np.hypot(arriving[:, 0], arriving[:, 1])[:, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)  # to the left of the direction of travel
    left_wall, right_wall = xy + left[:, None] * normal, xy - right[:, None] * normal
    if closed:
        left_wall, right_wall = np.vstack([left_wall, left_wall[:1]]), np.vstack([right_wall, right_wall[:1]])
    left_wall, right_wall = _pose(left_wall, right_wall, xy[0], tangent[0], config.start_line_y)
    _check_crossings(path, left_wall, right_wall, lines, closed)
    return Track(left_wall, right_wall, closed=closed, name=path.stem)


def _pose(left: np.ndarray, right: np.ndarray, first: np.ndarray, heading: np.ndarray,
          start_line_y: float) -> tuple[np.ndarray, np.ndarray]:
    """Move and turn the walls so that the first point is at (0, start_line_y), heading along +y."""
    # The rotation taking ``heading`` to (0, 1): x' = hy * x - hx * y, y' = hx * x + hy * y.
    hx, hy = heading
    rotation = np.array([[hy, -hx], [hx, hy]])

    def place(points: np.ndarray) -> np.ndarray:
        return (points - first) @ rotation.T + np.array([0.0, start_line_y])

    return place(left), place(right)


def _check_crossings(path: Path, left: np.ndarray, right: np.ndarray, lines: list[int], closed: bool) -> None:
    """Refuse walls that cross themselves or each other (neighbouring segments of a wall touch)."""
    n = len(left) - 1
    a = np.concatenate([left[:-1], right[:-1]])  # segment k: left wall of checkpoint k; n + k: right wall
    b = np.concatenate([left[1:], right[1:]])
    index = np.arange(2 * n)
    for start in range(0, 2 * n, 256):
        rows = slice(start, min(start + 256, 2 * n))
        hit = _segments_cross(a[rows, None], b[rows, None], a[None], b[None])
        i, j = index[rows, None], index[None]
        same_wall = (i < n) == (j < n)
        gap = np.abs((i % n) - (j % n))
        neighbours = same_wall & ((gap <= 1) | (closed & (gap == n - 1)))
        hit &= ~neighbours & (j > i)
        if hit.any():
            first, second = (int(v) for v in np.argwhere(hit)[0])
            first += start
            raise TrackFileError(f"{path}: the walls cross themselves: the {_describe(first, n, lines)} crosses "
                                 f"the {_describe(second, n, lines)}")


def _describe(segment: int, n: int, lines: list[int]) -> str:
    wall, k = ("left", segment) if segment < n else ("right", segment - n)
    return f"{wall} wall between the points of lines {lines[k]} and {lines[(k + 1) % len(lines)]}"


def _segments_cross(a, b, c, d) -> np.ndarray:
    """Whether segments a-b and c-d share a point (touching counts), broadcasting over leading axes."""
    def orient(p, q, r):
        return (q[..., 0] - p[..., 0]) * (r[..., 1] - p[..., 1]) - (q[..., 1] - p[..., 1]) * (r[..., 0] - p[..., 0])

    d1, d2, d3, d4 = orient(c, d, a), orient(c, d, b), orient(a, b, c), orient(a, b, d)
    proper = (d1 * d2 <= 0) & (d3 * d4 <= 0)
    collinear = (d1 == 0) & (d2 == 0)
    overlap = collinear & _boxes_overlap(a, b, c, d)
    return np.where(collinear, overlap, proper)


def _boxes_overlap(a, b, c, d) -> np.ndarray:
    lo1, hi1 = np.minimum(a, b), np.maximum(a, b)
    lo2, hi2 = np.minimum(c, d), np.maximum(c, d)
    return ((lo1 <= hi2) & (lo2 <= hi1)).all(axis=-1)


def save_track(track: Track, path: Path | str, scale: float = 1.0) -> Path:
    """Write ``track`` in the file format: each point the midpoint of its two wall points, its
    widths half their distance (divided by ``scale``); a circuit without its closing point."""
    path = Path(path)
    left, right = track.left_wall, track.right_wall
    if track.closed:
        left, right = left[:-1], right[:-1]
    centre = (left + right) / 2
    half = np.hypot(*(left - right).T) / 2
    what = f"the track of seed {track.seed}" if track.seed is not None else (track.name or "a track")
    lines = [f"# {what}, written by racing.track_file.save_track", f"# closed: {str(track.closed).lower()}",
             f"# scale: {scale!r}", "# " + ",".join(COLUMNS)]
    lines += [f"{x / scale!r},{y / scale!r},{w / scale!r},{w / scale!r}"
              for (x, y), w in zip(centre.tolist(), half.tolist())]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def track_config(track: Track, config: RacingConfig) -> RacingConfig:
    """``config`` with ``num_segments`` set to the track's checkpoints (a file decides how many)."""
    import dataclasses

    return dataclasses.replace(config, num_segments=track.num_checkpoints)


def parse_track(option: str, text: str) -> int | str:
    """A command line's track: a seed (digits), or the path of a track file, loaded once to check it;
    ``TrackFileError`` saying which (``option`` names the argument)."""
    if text.isdigit():
        if int(text) >= 2**32:
            raise TrackFileError(f"{option} must be a seed in [0, 2**32) or a track file, got {text}")
        return int(text)
    try:
        load_track(text)
    except TrackFileError as err:
        raise TrackFileError(f"{option}: {err}") from None
    return text


def env_track(owner: str, seeded: bool, track_file, track_scale, track_closed,
              keywords: dict) -> tuple[Track | None, RacingConfig]:
    """An environment's file track (None without ``track_file``) and its config; ``seeded``: the
    environment was also given track seeds (refused with a file)."""
    if track_file is not None:
        if seeded:
            raise ValueError("give track seeds or a track_file, not both")
        return file_track(track_file, keywords, owner, track_scale, track_closed)
    if track_scale is not None or track_closed is not None:
        raise ValueError("track_scale and track_closed apply to a track_file")
    return None, RacingConfig.from_keywords(owner, **keywords)


def file_track(track_file: Path | str, keywords: dict, owner: str, scale: float | None = None,
               closed: bool | None = None) -> tuple[Track, RacingConfig]:
    """An environment's file track and its config (``keywords``: its RacingConfig fields, without
    ``num_segments``, which the file decides)."""
    if "num_segments" in keywords:
        raise ValueError(f"{owner}: num_segments comes from the track file ({track_file}); do not give it")
    config = RacingConfig.from_keywords(owner, **keywords)
    track = load_track(track_file, scale, closed, config)
    return track, track_config(track, config)
