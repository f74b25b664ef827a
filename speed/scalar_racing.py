"""A plain-Python, one-car transcription of the racing rules (floats and ``math`` only).

This is the speed baseline of ``speed/env_speed.py`` and an independent oracle in the
tests; the environments never use it (their physics lives in ``racing.physics``). It is
written the straightforward way on purpose: scalar loops, a polygon test per checkpoint,
and a ray scan that stops at the first crossing, as the reference simulator did.
"""

from __future__ import annotations

import math

import numpy as np

from racing.config import RacingConfig


def _rad(degrees: float) -> float:
    return degrees / 180.0 * math.pi


def _inside(x: float, y: float, poly: list[tuple[float, float]]) -> bool:
    inside = False
    p1x, p1y = poly[-1]
    for p2x, p2y in poly:
        if min(p1y, p2y) < y <= max(p1y, p2y) and x <= max(p1x, p2x):
            if p1x == p2x or x <= (y - p1y) * (p2x - p1x) / (p2y - p1y) + p1x:
                inside = not inside
        p1x, p1y = p2x, p2y
    return inside


class ScalarRacing:
    """One car on the track laid out by ``RandomState(seed)``; ``reset`` continues that stream.

    ``nearest=True`` scans every wall segment ahead and keeps the nearest crossing (the
    spec's definition taken literally, with no early exit) instead of stopping at the
    first crossing in scan order as the reference did.
    """

    def __init__(self, seed: int, config: RacingConfig = RacingConfig(), nearest: bool = False):
        self.config = config
        self.nearest = nearest
        self.rng = np.random.RandomState(seed)
        left, right = [(-config.half_width, config.start_line_y)], [(config.half_width, config.start_line_y)]
        px = py = 0.0
        heading = 90.0
        for _ in range(config.num_segments):
            heading += (self.rng.rand() - 0.5) * config.max_turn_deg
            px += config.segment_length * math.cos(_rad(heading))
            py += config.segment_length * math.sin(_rad(heading))
            for wall, side in ((left, 90.0), (right, -90.0)):
                wall.append((px + config.half_width * math.cos(_rad(heading + side)),
                             py + config.half_width * math.sin(_rad(heading + side))))
        self.left, self.right = left, right
        self.quads = [[left[i], left[i + 1], right[i + 1], right[i]] for i in range(config.num_segments)]
        self.centres = [(sum(p[0] for p in q) / 4.0, sum(p[1] for p in q) / 4.0) for q in self.quads]

    def reset(self) -> list[float]:
        self.x = self.rng.rand() - 0.5
        self.y = self.rng.rand() - 0.5
        self.theta = _rad((self.rng.rand() - 0.5) * self.config.start_heading_deg)
        self.speed = 0.0
        self.checkpoint = 0
        self.t = 0
        return self.observe()

    def step(self, throttle: float, steer: float) -> tuple[list[float], float, bool, bool]:
        cfg = self.config
        throttle, steer = min(max(float(throttle), -1.0), 1.0), min(max(float(steer), -1.0), 1.0)
        target = (throttle / 2 + 0.5) * cfg.max_speed
        self.speed += (target - self.speed) * cfg.accel
        self.theta -= steer * self.speed / max(self.speed ** 2 / cfg.turn_rate, cfg.min_turn_radius)
        old_x, old_y = self.x, self.y
        self.x += math.sin(self.theta) * self.speed
        self.y += math.cos(self.theta) * self.speed
        reward = self.speed / cfg.max_speed
        terminated = False
        c, last = self.checkpoint, cfg.num_segments - 1
        if not _inside(self.x, self.y, self.quads[c]):
            if c < last and _inside(self.x, self.y, self.quads[c + 1]):
                self.checkpoint = c + 1
            elif c == last and self._crosses_finish(old_x, old_y):
                terminated = True
            else:
                reward -= cfg.crash_penalty
                c = self.checkpoint = max(c - 1, 0)
                self.x, self.y = self.centres[c]
                self.speed = 0.0
                dx = self.centres[c + 1][0] - self.centres[c][0]
                dy = self.centres[c + 1][1] - self.centres[c][1]
                self.theta = math.pi / 2 - math.atan2(dy, dx)
        self.t += 1
        return self.observe(), reward, terminated, self.t >= cfg.max_steps

    def _crosses_finish(self, old_x: float, old_y: float) -> bool:
        (ax, ay), (bx, by) = self.left[-1], self.right[-1]

        def side(px, py, qx, qy, rx, ry):
            return (qx - px) * (ry - py) - (qy - py) * (rx - px)

        d1 = side(ax, ay, bx, by, old_x, old_y)
        d2 = side(ax, ay, bx, by, self.x, self.y)
        d3 = side(old_x, old_y, self.x, self.y, ax, ay)
        d4 = side(old_x, old_y, self.x, self.y, bx, by)
        return d1 * d2 <= 0 and d3 * d4 <= 0 and d1 != d2

    def observe(self) -> list[float]:
        cfg = self.config
        heading_deg = self.theta / math.pi * 180.0
        readings = [self._ray(_rad(90.0 + a - heading_deg)) / cfg.ray_length for a in cfg.ray_angles_deg]
        return readings + [self.speed / cfg.max_speed]

    def _ray(self, phi: float) -> float:
        dx, dy = math.cos(phi), math.sin(phi)
        ox, oy = self.x, self.y
        length = self.config.ray_length
        best = length
        for i in range(self.checkpoint, self.config.num_segments):
            for wall in (self.left, self.right):
                (p1x, p1y), (p2x, p2y) = wall[i], wall[i + 1]
                v1x, v1y = ox - p1x, oy - p1y
                v2x, v2y = p2x - p1x, p2y - p1y
                denom = v2x * -dy + v2y * dx
                if denom == 0.0:
                    continue
                t1 = (v2x * v1y - v2y * v1x) / denom
                t2 = (v1x * -dy + v1y * dx) / denom
                if 0.0 <= t1 <= length and 0.0 <= t2 <= 1.0:
                    if not self.nearest:
                        return t1
                    best = min(best, t1)
        return best
