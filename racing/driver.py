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
