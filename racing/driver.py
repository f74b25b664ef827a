"""A hand-written driver that reads the rays: a reference point for learned policies and a test tool."""

from __future__ import annotations

import numpy as np


def ray_follower(observation: np.ndarray, steer_gain: float = 3.0) -> np.ndarray:
    """Steer toward the side whose rays see farther; go faster the more open the road ahead.

    Works on one observation (6,) or a batch (N, 6); returns float32 actions in [-1, 1].
    """
    obs = np.asarray(observation, dtype=np.float64)
    right, left, ahead = obs[..., 0] + obs[..., 1], obs[..., 3] + obs[..., 4], obs[..., 2]
    steer = np.clip(steer_gain * (left - right), -1.0, 1.0)
    throttle = np.clip(2.5 * ahead - 1.2, -1.0, 1.0)
    return np.stack([throttle, steer], axis=-1).astype(np.float32)


class PurePursuit:
    """A pure-pursuit controller on the track's centre line: it sees the true state (position,
    heading, checkpoint) and the track, like the oracle, but plans nothing.

    It aims at the point of the centre line (the checkpoints' centres) ``lookahead`` pixels
    ahead of the car's checkpoint, steers by the angle to it (``steer_gain`` per radian) and
    lifts the throttle as that angle grows (``slow_down`` per radian). Its constants were set by
    reasoning about the car (a turn radius of at least 75 px, 50 px per step at full speed), not
    fitted to any track. ``act(sim, car)`` returns ``[throttle, steering]``."""

    def __init__(self, lookahead: float = 250.0, steer_gain: float = 2.0, slow_down: float = 1.5):
        self.lookahead, self.steer_gain, self.slow_down = lookahead, steer_gain, slow_down

    def reset(self) -> None:
        """Nothing to forget between episodes (the interface of ``racing.oracle.Oracle``)."""

    def act(self, sim, car: int = 0) -> np.ndarray:
        track = sim.tracks[car]
        x, y, theta = float(sim.x[car]), float(sim.y[car]), float(sim.theta[car])
        centres, n = track.centres, track.num_checkpoints
        target, c = centres[int(sim.checkpoint[car])], int(sim.checkpoint[car])
        for step in range(n):  # the first centre at least ``lookahead`` away, along the track
            k = c + step
            if k >= n and not track.closed:
                target = (track.left_wall[-1] + track.right_wall[-1]) / 2  # the finish line's middle
                break
            target = centres[k % n]
            if np.hypot(target[0] - x, target[1] - y) >= self.lookahead:
                break
        hx, hy = np.sin(theta), np.cos(theta)  # heading: theta 0 is +y
        dx, dy = target[0] - x, target[1] - y
        angle = float(np.arctan2(hx * dy - hy * dx, hx * dx + hy * dy))  # > 0: the target is to the left
        steer = float(np.clip(self.steer_gain * angle, -1.0, 1.0))
        throttle = float(np.clip(1.0 - self.slow_down * abs(angle), -1.0, 1.0))
        return np.array([throttle, steer], dtype=np.float32)
