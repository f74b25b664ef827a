"""The racing physics, batched over cars: the one implementation both environments use.

Everything here is NumPy float64 and branch-free across cars. Per track, the geometry
each step needs is precomputed into tables with one row per checkpoint, so that a step
gathers one row per car (by its track slot and checkpoint) instead of looping:

* ``edges``: the four edges of checkpoint ``c`` and of ``c + 1``, ready for the even-odd
  point-in-polygon test;
* ``respawn``: where a car that leaves the track from checkpoint ``c`` is put back;
* ``rays``: the wall segments a ray can reach from checkpoint ``c``, in the reference's
  scan order. Culling is exact: a segment is dropped only when it lies farther than the
  ray length from every point a car with that checkpoint can occupy, so it can never
  be crossed within range and the readings are unchanged.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from racing.config import RacingConfig
from racing.track import Track, deg_to_rad

# Columns of an edge row of the point-in-polygon test.
_YMIN, _YMAX, _XMAX, _P1X, _P1Y, _DX, _DY = range(7)
# An edge that can never toggle the test (pads the missing checkpoint after the last).
_NEUTRAL_EDGE = (np.inf, -np.inf, 0.0, 0.0, 0.0, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class TrackTables:
    """Per-checkpoint lookup tables of one track (see the module docstring)."""

    # The checkpoint is the last axis, so that gathering one row per car gives car-last arrays.
    edges: np.ndarray  # (7, 2, 4, N): edge columns of checkpoint c (polygon 0) and c + 1 (1)
    respawn: np.ndarray  # (4, N): checkpoint, x, y, theta after leaving the track from c
    finish: np.ndarray  # (4,): the far edge of the last checkpoint, left[N] -> right[N]
    rays: np.ndarray  # (4, W, N): p1x, p1y, v2x, v2y of the wall segments reachable from c

    @property
    def width(self) -> int:
        return self.rays.shape[1]


def build_tables(track: Track, config: RacingConfig) -> TrackTables:
    n = track.num_checkpoints
    if n != config.num_segments:
        raise ValueError(f"track has {n} checkpoints but config.num_segments is {config.num_segments}")
    quads = np.stack([track.checkpoint(i) for i in range(n)])  # (N, 4, 2)

    # Edges p1 -> p2 in the reference's order (0-1, 1-2, 2-3, 3-0).
    p1, p2 = quads, np.roll(quads, -1, axis=1)
    dx, dy = p2[..., 0] - p1[..., 0], p2[..., 1] - p1[..., 1]
    edges = np.stack([np.minimum(p1[..., 1], p2[..., 1]), np.maximum(p1[..., 1], p2[..., 1]),
                      np.maximum(p1[..., 0], p2[..., 0]), p1[..., 0], p1[..., 1], dx,
                      np.where(dy == 0.0, 1.0, dy)], axis=-1)  # a flat edge never toggles
    neutral = np.broadcast_to(np.array(_NEUTRAL_EDGE), (1, 4, 7))
    after_last = edges[:1] if track.closed else neutral  # a circuit's checkpoint 0 follows its last
    edges = np.stack([edges, np.concatenate([edges[1:], after_last])], axis=1)  # (N, 2, 4, 7)

    back = np.maximum(np.arange(n) - 1, 0)  # leaving the track costs one checkpoint
    centres = track.centres
    respawn = np.stack([back, centres[back, 0], centres[back, 1],
                        np.array([track.respawn_heading(b) for b in back.tolist()])])
    # A circuit has no finish: a segment of NaN is never crossed (its laps are counted as checkpoint 0 follows the last)
    finish = np.full(4, np.nan) if track.closed else np.concatenate([track.left_wall[-1], track.right_wall[-1]])
    return TrackTables(np.ascontiguousarray(edges.transpose(3, 1, 2, 0)),
                       respawn, finish, _ray_table(track, quads, config))


def _ray_table(track: Track, quads: np.ndarray, config: RacingConfig) -> np.ndarray:
    """Reachable wall segments per checkpoint, in scan order (checkpoint, then left, right)."""
    n = track.num_checkpoints
    # Segment 2i is the left wall of checkpoint i, 2i + 1 its right wall.
    p1 = np.stack([track.left_wall[:-1], track.right_wall[:-1]], axis=1).reshape(2 * n, 2)
    p2 = np.stack([track.left_wall[1:], track.right_wall[1:]], axis=1).reshape(2 * n, 2)
    # A car with checkpoint c is inside that checkpoint (hence within its corners' circle),
    # or at most one step beyond it when it has just finished; at reset it is near the origin.
    centres = track.centres
    radius = np.linalg.norm(quads - centres[:, None], axis=-1).max(axis=1) + config.max_speed
    start_box = np.array([[-0.5, -0.5], [-0.5, 0.5], [0.5, -0.5], [0.5, 0.5]])
    radius[0] = max(radius[0], np.linalg.norm(start_box - centres[0], axis=-1).max())
    reach = radius + config.ray_length * (1 + 1e-9) + 1e-6
    distance = _point_segment_distance(centres[:, None], p1[None], p2[None])  # (N, 2N)
    # Scan order from checkpoint c: the walls of c, c + 1, ...; on a circuit on past the last to c - 1.
    order = (2 * np.arange(n)[:, None] + np.arange(2 * n)[None]) % (2 * n)  # (N, 2N) segment indices
    if not track.closed:
        order = np.where(order >= 2 * np.arange(n)[:, None], order, -1)  # walls of c, c+1, ... only
    reachable = (order >= 0) & (np.take_along_axis(distance, np.maximum(order, 0), axis=1) <= reach[:, None])
    width = max(int(reachable.sum(axis=1).max()), 1)
    table = np.full((4, width, n), np.nan)  # NaN pads never cross a ray
    for c in range(n):
        segments = order[c][reachable[c]]
        table[:2, : len(segments), c] = p1[segments].T
        table[2:, : len(segments), c] = (p2[segments] - p1[segments]).T
    return table


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab, ap = b - a, p - a
    along = np.clip((ap * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(ap - along[..., None] * ab, axis=-1)


def inside_parity(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Even-odd test of points (x, y), shape (B,), against polygons given as edge columns.

    ``edges`` has shape (7, P, E, B): for each of B cars, P polygons of E edges. An edge
    toggles when ``ymin < y <= ymax`` and ``x <= xmax`` and ``x`` is left of the edge at
    height ``y``; returns (P, B) booleans. Cars are the innermost axis throughout.
    """
    ymin, ymax, xmax, p1x, p1y, dx, dy = edges
    crossing = (y - p1y) * dx / dy + p1x
    toggles = (y > ymin) & (y <= ymax) & (x <= xmax) & (x <= crossing)
    return np.logical_xor.reduce(toggles, axis=1)


def ray_distances(x: np.ndarray, y: np.ndarray, theta: np.ndarray, rays: np.ndarray,
                  config: RacingConfig, nearest: bool = False) -> np.ndarray:
    """Distance along each ray to the wall, capped at the ray length: shape (num_rays, B).

    ``rays`` (4, W, B) holds p1x, p1y, v2x, v2y of each car's reachable wall segments in
    scan order. As in the reference, a ray reads the first segment in scan order that it
    crosses within range; ``nearest=True`` takes the closest crossing instead (the two
    differ only where a track crosses itself within sensor range).
    """
    phi = deg_to_rad(_ray_offsets(config) - theta / np.pi * 180.0)  # (R, B)
    ux, uy = np.cos(phi)[:, None], np.sin(phi)[:, None]  # (R, 1, B)
    p1x, p1y, v2x, v2y = rays  # (W, B)
    v1x, v1y = x - p1x, y - p1y
    length = config.ray_length
    with np.errstate(divide="ignore", invalid="ignore"):  # parallel rays and NaN pads: no crossing
        denom = v2x * -uy + v2y * ux  # (R, W, B)
        t1 = (v2x * v1y - v2y * v1x) / denom
        t2 = (v1x * -uy + v1y * ux) / denom
    valid = (t1 >= 0.0) & (t1 <= length) & (t2 >= 0.0) & (t2 <= 1.0)
    if nearest:
        return np.where(valid, t1, length).min(axis=1)
    first = valid.argmax(axis=1)  # (R, B): the first crossing in scan order
    base, step = _gather_offsets(t1.shape)
    return np.where(valid.any(axis=1), t1.take(base + first * step), length)


@functools.lru_cache(maxsize=64)
def _gather_offsets(shape: tuple[int, int, int]) -> tuple[np.ndarray, int]:
    """Flat offsets into an (R, W, B) array of element (r, 0, b), and the stride of W."""
    r, w, b = shape
    base = np.arange(r)[:, None] * (w * b) + np.arange(b)
    base.flags.writeable = False  # shared by every caller
    return base, b


def _ray_offsets(config: RacingConfig) -> np.ndarray:
    """90 + a_k (degrees) per ray, shape (R, 1): the world angle of ray k for a car heading along +y."""
    return _offsets_of(config.ray_angles_deg)


@functools.lru_cache(maxsize=16)
def _offsets_of(ray_angles_deg: tuple[float, ...]) -> np.ndarray:
    offsets = 90.0 + np.array(ray_angles_deg)[:, None]
    offsets.flags.writeable = False  # shared by every caller
    return offsets


def crosses_segment(ax, ay, bx, by, px, py, qx, qy) -> np.ndarray:
    """Whether the step p -> q crosses segment a -> b (touching counts), elementwise."""
    d1 = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
    d2 = (bx - ax) * (qy - ay) - (by - ay) * (qx - ax)
    d3 = (qx - px) * (ay - py) - (qy - py) * (ax - px)
    d4 = (qx - px) * (by - py) - (qy - py) * (bx - px)
    return (d1 * d2 <= 0) & (d3 * d4 <= 0) & (d1 != d2)


# ------------------------------------------------------------------------------ one car
# One car pays for every NumPy call as if it were a batch: about 50 small calls per step,
# whose fixed cost dwarfs the arithmetic. For N = 1 the same tables are read as Python
# floats and the same operations run in the same order on scalars (IEEE double arithmetic,
# so the results are identical bit for bit); sines and cosines still come from NumPy, so the
# two paths agree on any NumPy build. tests/test_physics.py checks the two paths against
# each other on random tracks, and the conformance tests check both against the reference.


@dataclass(frozen=True, eq=False)
class CarTables:
    """``TrackTables`` as nested tuples of Python floats, one entry per checkpoint."""

    polygons: tuple  # [c]: checkpoint c's polygon and c + 1's, each 4 edges of the 7 edge columns
    respawn: tuple  # [c]: (checkpoint, x, y, theta) after leaving the track from c
    finish: tuple  # (ax, ay, bx, by)
    segments: tuple  # [c]: (p1x, p1y, v2x, v2y) of each reachable wall segment, in scan order


def car_tables(tables: TrackTables) -> CarTables:
    n = tables.edges.shape[-1]
    edges = tables.edges.transpose(3, 1, 2, 0).tolist()  # (N, 2, 4, 7)
    rays = tables.rays.transpose(2, 1, 0).tolist()  # (N, W, 4)
    respawn = tables.respawn.T.tolist()
    return CarTables(
        polygons=tuple(tuple(tuple(tuple(edge) for edge in polygon) for polygon in edges[c]) for c in range(n)),
        respawn=tuple((int(r[0]), r[1], r[2], r[3]) for r in respawn),
        finish=tuple(tables.finish.tolist()),
        segments=tuple(tuple(tuple(s) for s in rays[c] if s[0] == s[0]) for c in range(n)),  # drop NaN pads
    )


def _inside_car(x: float, y: float, polygon: tuple) -> bool:
    """``inside_parity`` for one point and one polygon."""
    inside = False
    for ymin, ymax, xmax, p1x, p1y, dx, dy in polygon:
        if y > ymin and y <= ymax and x <= xmax and x <= (y - p1y) * dx / dy + p1x:
            inside = not inside
    return inside


def step_car(x: float, y: float, theta: float, speed: float, checkpoint: int, throttle: float, steer: float,
             tables: CarTables, config: RacingConfig) -> tuple:
    """One step of one car, as ``RacingSim.step`` computes it for a batch.

    Returns ``(x, y, theta, speed, checkpoint, reward, finished, crashed)``.
    """
    throttle = min(max(throttle, -1.0), 1.0)
    steer = min(max(steer, -1.0), 1.0)
    speed = speed + ((throttle / 2 + 0.5) * config.max_speed - speed) * config.accel
    theta = theta - steer * speed / max(speed * speed / config.turn_rate, config.min_turn_radius)
    sin_cos = np.sin(theta), np.cos(theta)
    old_x, old_y = x, y
    x = old_x + float(sin_cos[0]) * speed
    y = old_y + float(sin_cos[1]) * speed
    reward = speed / config.max_speed
    current, following = tables.polygons[checkpoint]
    in_current = _inside_car(x, y, current)
    in_next = _inside_car(x, y, following)
    finished = crashed = False
    if in_current or in_next:
        checkpoint += not in_current and in_next
    else:
        if checkpoint == config.num_segments - 1:
            finished = bool(crosses_segment(*tables.finish, old_x, old_y, x, y))
        if not finished:
            crashed = True
            reward -= config.crash_penalty
            checkpoint, x, y, theta = tables.respawn[checkpoint]
            speed = 0.0
    return x, y, theta, speed, checkpoint, reward, finished, crashed


def ray_distances_car(x: float, y: float, theta: float, segments: tuple, config: RacingConfig,
                      nearest: bool = False) -> list[float]:
    """``ray_distances`` for one car: the reading of each ray, capped at the ray length."""
    length = config.ray_length
    phi = (np.asarray(_ray_offsets(config)[:, 0]) - theta / np.pi * 180.0) / 180.0 * np.pi
    directions = zip(np.cos(phi).tolist(), np.sin(phi).tolist())
    # Per segment, what does not depend on the ray: the car relative to its start, and t1's numerator.
    relative = [(v1x, v1y, v2x, v2y, v2x * v1y - v2y * v1x)
                for v1x, v1y, v2x, v2y in ((x - p1x, y - p1y, v2x, v2y) for p1x, p1y, v2x, v2y in segments)]
    readings = []
    for ux, uy in directions:
        best = length
        for v1x, v1y, v2x, v2y, numerator in relative:
            denom = v2x * -uy + v2y * ux
            if denom == 0.0:  # parallel: no crossing (the batched kernel gets inf or NaN here)
                continue
            t1 = numerator / denom
            if 0.0 <= t1 <= length:
                t2 = (v1x * -uy + v1y * ux) / denom
                if 0.0 <= t2 <= 1.0:
                    if not nearest:
                        best = t1
                        break
                    best = min(best, t1)
        readings.append(best)
    return readings
