"""Random race tracks: a chain of quadrilateral checkpoints between two walls.

A track is laid out from NumPy's legacy Mersenne Twister (``numpy.random.RandomState``),
one uniform draw per segment, which is what makes the paper's tracks reproducible from
their seeds. The same stream then goes on to draw the car's start states.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from racing.config import RacingConfig


@dataclass(frozen=True, eq=False)
class Track:
    """The walls of one track and the geometry derived from them.

    Checkpoint ``i`` (``0 <= i < num_segments``) is the quadrilateral
    ``[left_wall[i], left_wall[i + 1], right_wall[i + 1], right_wall[i]]``. On an open track
    (every generated one) the last checkpoint ends at the finish line; on a closed one (a
    circuit, from a file: ``racing.track_file``) checkpoint 0 follows the last, and the walls'
    last points repeat their first.
    """

    left_wall: np.ndarray  # (num_segments + 1, 2) float64
    right_wall: np.ndarray  # (num_segments + 1, 2) float64
    seed: int | None = None
    closed: bool = False  # a circuit: the walls' last points are their first, checkpoint 0 follows the last
    name: str | None = None  # a file track's (its file's stem)
    reading: object = field(default=None, repr=False)  # a file track's racing.track_file.Reading: how it was read
    centres: np.ndarray = field(init=False, repr=False)  # (num_segments, 2)

    def __post_init__(self) -> None:
        left = np.ascontiguousarray(self.left_wall, dtype=np.float64)
        right = np.ascontiguousarray(self.right_wall, dtype=np.float64)
        if left.ndim != 2 or left.shape[1] != 2 or left.shape != right.shape or len(left) < 3:
            raise ValueError(
                "left_wall and right_wall must both have shape (N + 1, 2) with N >= 2 checkpoints, "
                f"got {left.shape} and {right.shape}"
            )
        if not (np.isfinite(left).all() and np.isfinite(right).all()):
            raise ValueError("track walls must be finite")
        if self.closed and not (np.array_equal(left[0], left[-1]) and np.array_equal(right[0], right[-1])):
            raise ValueError("a closed track's walls must end at their first points")
        left.flags.writeable = False
        right.flags.writeable = False
        centres = (left[:-1] + left[1:] + right[1:] + right[:-1]) / 4.0
        centres.flags.writeable = False
        object.__setattr__(self, "left_wall", left)
        object.__setattr__(self, "right_wall", right)
        object.__setattr__(self, "centres", centres)

    @property
    def num_checkpoints(self) -> int:
        return len(self.left_wall) - 1

    def checkpoint(self, i: int) -> np.ndarray:
        """Corners of checkpoint ``i`` in polygon order, shape (4, 2)."""
        return np.stack(
            [self.left_wall[i], self.left_wall[i + 1], self.right_wall[i + 1], self.right_wall[i]]
        )

    def respawn_heading(self, i: int) -> float:
        """Heading (radians, 0 = +y) of a car put back at the centre of checkpoint ``i``.

        ``math.atan2`` (the C library's) rather than ``np.arctan2``, whose AVX-512 version rounds
        differently from the one every other x86-64 CPU runs."""
        dx, dy = self.centres[i + 1] - self.centres[i]
        return float(np.pi / 2 - math.atan2(dy, dx))

    def centre_line_length(self) -> float:
        """The length of the line through the midpoints of the wall points (a circuit's closing
        segment included), in pixels."""
        centre = (self.left_wall + self.right_wall) / 2
        return float(np.hypot(*np.diff(centre, axis=0).T).sum())

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower-left and upper-right corners of the box that holds both walls."""
        walls = np.concatenate([self.left_wall, self.right_wall])
        return walls.min(axis=0), walls.max(axis=0)


def layout_track(rng: np.random.RandomState, config: RacingConfig = RacingConfig(),
                 seed: int | None = None) -> Track:
    """Lay out a track with ``config.num_segments`` draws from ``rng``.

    Starting at the origin heading along +y, each segment turns by
    ``(U - 0.5) * max_turn_deg`` degrees and advances ``segment_length``; the walls lie
    ``half_width`` to each side of the centre line.
    """
    n = config.num_segments
    turns = (rng.random_sample(n) - 0.5) * config.max_turn_deg
    # Headings in degrees; np.cumsum adds in sequence, exactly as the reference's loop did.
    headings = np.cumsum(np.concatenate([[90.0], turns]))[1:]
    centre_line = np.cumsum(config.segment_length * _unit(headings), axis=0)
    hw, y0 = config.half_width, config.start_line_y
    left = np.concatenate([[[-hw, y0]], centre_line + hw * _unit(headings + 90.0)])
    right = np.concatenate([[[hw, y0]], centre_line + hw * _unit(headings - 90.0)])
    return Track(left, right, seed=seed)


def deg_to_rad(degrees):
    """Degrees to radians, rounded as the reference simulator rounded them (bit-exact tracks)."""
    return degrees / 180.0 * np.pi


def _unit(degrees: np.ndarray) -> np.ndarray:
    radians = deg_to_rad(degrees)
    return np.stack([np.cos(radians), np.sin(radians)], axis=-1)


def track_from_seed(seed: int, config: RacingConfig = RacingConfig()) -> Track:
    """The track that ``RandomState(seed)`` lays out (the paper's tracks by their seeds)."""
    return layout_track(np.random.RandomState(seed), config, seed=seed)
