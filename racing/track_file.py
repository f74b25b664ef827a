"""Tracks from files: a centre line with the track's width to each side, in CSV.

The columns are those of the TUM racetrack-database (``x_m, y_m, w_tr_right_m, w_tr_left_m``):
one row per centre-line point, its coordinates and the distance from it to the right and to
the left wall. A file of that database loads as it is downloaded. Lines starting with ``#``
are comments; two of them may say how to read the file:

    # closed: true      (a circuit: the last point joins the first)
    # scale: 16.0       (simulator units, pixels, per file unit)
    # x_m,y_m,w_tr_right_m,w_tr_left_m
    0.0,-10.0,100.0,100.0
    ...

A header row of the column names (with or without ``#``) is optional. Without those comments
a file is read the way a downloaded circuit needs:

* **closed** if its last point lies within ``CLOSING_GAP`` segment lengths (the median
  distance between its points) of its first, or repeats it; open otherwise;
* **scaled** so that the road's median width is a generated track's (``2 * half_width``,
  200 px): a file in metres then drives like the generated tracks (``scale_for``).

``load_track`` arguments override the comments, and the comments the rules. How a file was
read (scale, closed, where each came from, and what the car may not fit: a road narrower or a
checkpoint shorter than a step at full speed, a bend tighter than the car turns) is the
track's ``reading`` (``Reading``), which ``tracks.py check`` prints and runs record.

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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from door import files
from racing.config import RacingConfig
from racing.track import Track

COLUMNS = ("x_m", "y_m", "w_tr_right_m", "w_tr_left_m")
EXAMPLES = Path(__file__).resolve().parent / "tracks"  # the example files that ship with the package


class TrackFileError(ValueError):
    """A track file that cannot be loaded; the message names the line and the problem."""


class WallsCross(TrackFileError):
    """A file whose walls cross: ``track`` is what it would have been (to draw it, not to drive it), and
    ``segments`` the two crossing wall segments, each ``(from, to)`` in the track's coordinates."""

    def __init__(self, message: str, track: Track, segments: tuple[np.ndarray, np.ndarray]):
        super().__init__(message)
        self.track, self.segments = track, segments


# Why a file's walls may not cross, said with every such refusal.
CROSSING_HELP = ("a track here is flat: the car is inside one checkpoint at a time and its rays see every wall "
                 "ahead, so a circuit that passes over itself (a bridge or a tunnel, a figure-eight such as "
                 "Suzuka) cannot be represented, and walls that cross by mistake (a width too large at a "
                 "tight bend) are refused the same way; `python tracks.py show FILE` draws it with the "
                 "crossing marked")


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
    try:  # the door's rules: a device or a pipe is refused unopened, a larger file unread
        text = files.read(path, MAX_BYTES, "track file", follow=True).decode("utf-8-sig")
    except FileNotFoundError:
        raise TrackFileError(f"{path}: cannot be read (no such file)") from None
    except files.FileRefused as err:
        raise TrackFileError(str(err)) from None
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


MAX_EXTENT = 1e9  # pixels a scaled track may span (a car drives at most 5e7 in an episode: 50 px x 1e6 steps)
MIN_SEGMENT = 1e-3  # pixels: the shortest scaled segment the wall geometry is computed on (float64 rounding)
CLOSING_GAP = 2.0  # a file whose last point lies within this many segment lengths of its first is a circuit


@dataclass(frozen=True)
class Reading:
    """How a track file was read: its scale and shape, where each came from ("the caller", "the
    file" or the rule: "the road's width", "the geometry"), and what the car may not fit."""

    file: str
    scale: float
    scale_from: str
    closed: bool
    closed_from: str
    warnings: tuple[str, ...] = ()

    def record(self) -> dict:
        """As a run's ``summary.json`` records it."""
        return {"file": self.file, "scale": self.scale, "scale_from": self.scale_from, "closed": self.closed,
                "closed_from": self.closed_from, "warnings": list(self.warnings)}


def scale_for(points: np.ndarray, config: RacingConfig = RacingConfig()) -> float:
    """The scale (pixels per file unit, four significant digits) that gives the road of ``points``
    (rows ``x, y, right, left``) the median width of a generated track, ``2 * config.half_width``."""
    return float(f"{2 * config.half_width / float(np.median(points[:, 2] + points[:, 3])):.4g}")


def looks_closed(points: np.ndarray) -> bool:
    """Whether the file's last point lies within ``CLOSING_GAP`` segment lengths (the median
    distance between consecutive points) of its first, or repeats it."""
    xy = points[:, :2]
    steps = np.hypot(*np.diff(xy, axis=0).T)
    return bool(np.hypot(*(xy[-1] - xy[0])) <= CLOSING_GAP * float(np.median(steps)))


def load_track(path: Path | str, scale: float | None = None, closed: bool | None = None,
               config: RacingConfig = RacingConfig()) -> Track:
    """The track of a file (see the module docstring), its ``reading`` saying how it was read;
    ``TrackFileError`` if it is not one."""
    path = Path(path)
    points, lines, settings = read_rows(path)
    if len(points) < 3:
        raise TrackFileError(f"{path}: {len(points)} point(s); a track needs at least 3 (2 checkpoints)")
    closed, closed_from = ((bool(closed), "the caller") if closed is not None
                           else (settings["closed"], "the file") if "closed" in settings
                           else (looks_closed(points), "the geometry"))
    scale, scale_from = ((scale, "the caller") if scale is not None
                         else (settings["scale"], "the file") if "scale" in settings
                         else (scale_for(points, config), "the road's width"))
    if isinstance(scale, bool) or not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
        raise TrackFileError(f"{path}: scale must be a number > 0, got {scale!r}")
    scale = float(scale)
    if closed and len(points) > 3 and np.array_equal(points[0, :2], points[-1, :2]):
        points, lines = points[:-1], lines[:-1]  # a circuit written with its first point repeated at the end
    xy, right, left = points[:, :2] * scale, points[:, 2] * scale, points[:, 3] * scale
    extent = float(np.ptp(xy, axis=0).max()) + 2 * float(max(right.max(), left.max()))
    if not extent <= MAX_EXTENT:
        raise TrackFileError(f"{path}: scale {scale:g} makes the track {extent:.3g} px across; at most {MAX_EXTENT:.0e} "
                             "(a car drives at most 5e7 px in an episode)")
    steps = np.diff(np.vstack([xy, xy[:1]]) if closed else xy, axis=0)
    lengths = np.hypot(steps[:, 0], steps[:, 1])
    if (lengths == 0).any():
        i = int(np.flatnonzero(lengths == 0)[0])
        after = lines[(i + 1) % len(lines)]
        raise TrackFileError(f"{path}, line {after}: repeats the point of line {lines[i]}")
    if lengths.min() < MIN_SEGMENT:
        i = int(np.argmin(lengths))
        raise TrackFileError(f"{path}, line {lines[(i + 1) % len(lines)]}: at scale {scale:g} it lies {lengths[i]:.2g} px "
                             f"from the point before it, below {MIN_SEGMENT:g} px (too small to compute walls on); "
                             "give a larger scale")
    arriving = np.vstack([steps[-1:], steps[:-1]]) if closed else np.vstack([steps[:1], steps])  # (M, 2)
    tangent = arriving / np.hypot(arriving[:, 0], arriving[:, 1])[:, None]
    normal = np.stack([-tangent[:, 1], tangent[:, 0]], axis=1)  # to the left of the direction of travel
    left_wall, right_wall = xy + left[:, None] * normal, xy - right[:, None] * normal
    if closed:
        left_wall, right_wall = np.vstack([left_wall, left_wall[:1]]), np.vstack([right_wall, right_wall[:1]])
    left_wall, right_wall = _pose(left_wall, right_wall, xy[0], tangent[0], config.start_line_y)
    _check_crossings(path, left_wall, right_wall, lines, closed)
    reading = Reading(str(path), scale, scale_from, closed, closed_from,
                      fit_warnings(xy, right + left, lengths, lines, closed, config))
    return Track(left_wall, right_wall, closed=closed, name=path.stem, reading=reading)


def fit_warnings(xy: np.ndarray, widths: np.ndarray, lengths: np.ndarray, lines: list[int], closed: bool,
                 config: RacingConfig) -> tuple[str, ...]:
    """What the car may not fit on a track of centre points ``xy`` and road ``widths`` (pixels;
    ``lengths``: each checkpoint's centre-line length): a road narrower than a step at full speed,
    a checkpoint shorter than one (a car at full speed skips it, which counts as leaving the
    track), a bend whose radius is below the car's smallest turning radius at any speed."""
    found = []
    step, turn = config.max_speed, config.min_turn_radius

    def where(mask: np.ndarray, value: np.ndarray, what: str) -> None:
        if mask.any():
            i = int(np.argmin(np.where(mask, value, np.inf)))
            more = int(mask.sum()) - 1
            found.append(what.format(value=float(value[i]), line=lines[i], next=lines[(i + 1) % len(lines)])
                         + (f" (and at {more:,} more)" if more else ""))

    where(widths < step, widths, "the road is {value:.0f} px wide at line {line}, narrower than a step at full speed "
          f"({step:g} px)")
    where(lengths < step, lengths, "the checkpoint from line {line} to line {next} is {value:.0f} px long, shorter "
          f"than a step at full speed ({step:g} px): a car at full speed skips it and counts as leaving the track")
    ring = np.vstack([xy[-1:], xy, xy[:1]]) if closed else xy
    a, b, c = ring[:-2], ring[1:-1], ring[2:]
    twice_area = np.abs((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))
    sides = np.hypot(*(b - a).T) * np.hypot(*(c - b).T) * np.hypot(*(c - a).T)
    with np.errstate(divide="ignore"):
        radius = np.concatenate([[np.inf] * (not closed), sides / (2 * twice_area), [np.inf] * (not closed)])
    where(radius < turn, radius, "the centre line bends with a radius of {value:.0f} px at line {line}, tighter "
          f"than the car turns at any speed ({turn:g} px)")
    if found:
        found.append("scale the file up (a larger scale) or see docs/usage.md, 'Bring your own circuit'")
    return tuple(found)


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
    """Refuse walls that cross themselves or each other (neighbouring segments of a wall touch): ``WallsCross``."""
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
            raise WallsCross(f"{path}: the walls cross themselves: the {_describe(first, n, lines)} crosses "
                             f"the {_describe(second, n, lines)} ({CROSSING_HELP})",
                             Track(left, right, closed=closed, name=path.stem),
                             ((a[first], b[first]), (a[second], b[second])))


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
    files.folder(path.parent, path.parent, create=True)
    files.write_text(path, "\n".join(lines) + "\n")
    return path


def make_circuit(points: int = 1200, spacing: float = 5.0) -> np.ndarray:
    """A circuit in the TUM racetrack-database's layout: ``points`` centre-line points ``spacing``
    metres apart (closed: the last lies one spacing from the first, which is not repeated), a road
    of 10 to 13 m. Its rows ``x_m, y_m, w_tr_right_m, w_tr_left_m``; ``write_rows`` saves them as
    a downloaded file is (a header comment, no settings). A bean of radius ``r(phi) = R (1 + 0.25
    cos 2 phi - 0.2 cos 3 phi)``, sized so that the centre line is ``points * spacing`` long."""
    if isinstance(points, bool) or not isinstance(points, int) or not 3 <= points <= MAX_ROWS:
        raise ValueError(f"points must be an integer in [3, {MAX_ROWS:,}], got {points!r}")
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be a number > 0, got {spacing!r}")
    phi = np.linspace(0.0, 2 * np.pi, 20_001)
    radius = 1 + 0.25 * np.cos(2 * phi) - 0.2 * np.cos(3 * phi)
    xy = np.stack([radius * np.cos(phi), radius * np.sin(phi)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    at = np.arange(points) * (arc[-1] / points)  # equally spaced along the curve, the start not repeated
    angle = np.interp(at, arc, phi)
    r = 1 + 0.25 * np.cos(2 * angle) - 0.2 * np.cos(3 * angle)
    size = points * spacing / arc[-1]
    x, y = size * r * np.cos(angle), size * r * np.sin(angle)
    right, left = 5.5 + 0.5 * np.sin(3 * angle), 5.8 + 0.6 * np.cos(2 * angle)
    return np.stack([x, y, right, left], axis=1)


def write_rows(path: Path | str, rows: np.ndarray) -> Path:
    """Save rows ``x, y, right, left`` as the TUM racetrack-database's files are: its header as a
    comment, three decimals, no ``closed`` or ``scale`` comment."""
    path = Path(path)
    lines = ["# " + ",".join(COLUMNS)] + [f"{x:.3f},{y:.3f},{r:.3f},{l:.3f}" for x, y, r, l in rows.tolist()]
    files.write_text(path, "\n".join(lines) + "\n")
    return path


def track_config(track: Track, config: RacingConfig) -> RacingConfig:
    """``config`` with ``num_segments`` set to the track's checkpoints (a file decides how many)."""
    import dataclasses

    return dataclasses.replace(config, num_segments=track.num_checkpoints)


@dataclass(frozen=True)
class FileTrack:
    """A track file as a tool names it, with the scale and closure its caller gave (None: the
    file's comment, else the rule; see the module docstring). Printed, it is its path."""

    path: str
    scale: float | None = None
    closed: bool | None = None

    def __str__(self) -> str:
        return self.path


def env_keywords(track: "int | str | FileTrack") -> dict:
    """The environment keywords that put a car on ``track``: a seed, a track file's path, or a
    ``FileTrack`` (``racing.RacingEnv(**env_keywords(track))``)."""
    if isinstance(track, FileTrack):
        return {"track_file": track.path, "track_scale": track.scale, "track_closed": track.closed}
    return {"track_file": str(track)} if isinstance(track, (str, Path)) else {"track_seed": track}


def add_track_options(parser) -> None:
    """``--track-scale`` and ``--track-closed`` / ``--track-open``: how every tool that takes a
    track file overrides the file's scale and closure (``train.py``: ``env.track_scale``,
    ``env.track_closed``)."""
    parser.add_argument("--track-scale", type=float, default=None, metavar="S",
                        help="a track file's pixels per file unit (default: the file's '# scale:' comment, else "
                             "the scale that makes its road 200 px wide, as generated tracks are)")
    shape = parser.add_mutually_exclusive_group()
    shape.add_argument("--track-closed", dest="track_closed", action="store_const", const=True, default=None,
                       help="read a track file as a circuit (default: its '# closed:' comment, else its geometry)")
    shape.add_argument("--track-open", dest="track_closed", action="store_const", const=False,
                       help="read a track file as open, start to finish")


def parse_track(option: str, text: str, scale: float | None = None, closed: bool | None = None) -> "int | FileTrack":
    """A command line's track: a seed (digits), or a track file (a ``FileTrack`` with the caller's
    ``scale`` and ``closed``), loaded once to check it; ``TrackFileError`` saying which (``option``
    names the argument)."""
    if text.isdigit():
        if int(text) >= 2**32:
            raise TrackFileError(f"{option} must be a seed in [0, 2**32) or a track file, got {text}")
        if scale is not None or closed is not None:
            raise TrackFileError(f"--track-scale, --track-closed and --track-open apply to a track file; {option} "
                                 f"is the seed {text}")
        return int(text)
    try:
        load_track(text, scale, closed)
    except TrackFileError as err:
        raise TrackFileError(f"{option}: {err}") from None
    return FileTrack(text, scale, closed)


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
