"""Every constant of the racing task, in one validated, immutable place.

The defaults are those of the paper's environment. All of them may be overridden,
for instance ``RacingConfig(num_segments=10, max_steps=500)``; the Gymnasium and
TorchRL environments accept the same keywords.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


MAX_SEGMENTS = 5_000  # a track's checkpoints (the paper's: 50); the ray tables' building grows with their square
MAX_STEPS = 1_000_000  # an episode's steps (the paper's: 200); a run keeps each episode's transitions
MAX_RAYS = 64  # distance rays (the paper's: 5); each is an observation of every stored transition


@dataclass(frozen=True)
class RacingConfig:
    """Constants of track generation, car dynamics, sensors and episodes (sizes bounded:
    ``MAX_SEGMENTS``, ``MAX_STEPS``, ``MAX_RAYS``)."""

    # Track layout (pixels and degrees).
    num_segments: int = 50  # checkpoints (quadrilaterals) per track
    segment_length: float = 200.0  # distance between consecutive centre-line points
    half_width: float = 100.0  # centre line to each wall
    max_turn_deg: float = 75.0  # a segment turns by (U - 0.5) * max_turn_deg, U ~ U[0, 1)
    start_line_y: float = -10.0  # y of the first wall points (-half_width, y), (half_width, y)
    # Car dynamics (one step = one frame).
    max_speed: float = 50.0  # pixels per step at full throttle
    accel: float = 0.05  # fraction of the gap to the target speed closed per step
    turn_rate: float = 2.0  # steering: theta -= w * v / max(v**2 / turn_rate, min_turn_radius)
    min_turn_radius: float = 75.0
    start_heading_deg: float = 10.0  # reset heading is uniform in +-start_heading_deg / 2
    # Sensors.
    ray_length: float = 500.0  # sensor range, also the normaliser of the readings
    ray_angles_deg: tuple[float, ...] = (-45.0, -22.5, 0.0, 22.5, 45.0)  # right to left
    # Rewards and episodes.
    crash_penalty: float = 10.0  # subtracted from the reward of a step that leaves the track
    max_steps: int = 200  # time limit (truncation)
    laps: int = 0  # on a circuit (a closed track file): the episode ends after this many laps; 0: no lap limit

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "ray_angles_deg", tuple(float(a) for a in self.ray_angles_deg))
        except (TypeError, ValueError):
            raise ValueError(f"Invalid RacingConfig: ray_angles_deg must be a sequence of angles in degrees, "
                             f"got {self.ray_angles_deg!r}") from None
        problems = []
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "ray_angles_deg":
                if len(value) == 0 or not all(math.isfinite(a) for a in value):
                    problems.append("ray_angles_deg must be a non-empty sequence of finite angles")
                elif len(value) > MAX_RAYS:
                    problems.append(f"ray_angles_deg holds {len(value):,} rays, more than {MAX_RAYS}")
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                problems.append(f"{f.name} must be a number, got {value!r}")
            elif not math.isfinite(value):
                problems.append(f"{f.name} must be finite, got {value!r}")
        if not problems:
            if not isinstance(self.num_segments, int) or not 2 <= self.num_segments <= MAX_SEGMENTS:
                problems.append(f"num_segments must be an integer in [2, {MAX_SEGMENTS:,}], got {self.num_segments!r}")
            if not isinstance(self.max_steps, int) or not 1 <= self.max_steps <= MAX_STEPS:
                problems.append(f"max_steps must be an integer in [1, {MAX_STEPS:,}], got {self.max_steps!r}")
            if not isinstance(self.laps, int) or self.laps < 0:
                problems.append(f"laps must be an integer >= 0 (0: no lap limit), got {self.laps!r}")
            for name in ("segment_length", "half_width", "max_speed", "turn_rate",
                         "min_turn_radius", "ray_length"):
                if getattr(self, name) <= 0:
                    problems.append(f"{name} must be > 0, got {getattr(self, name)!r}")
            if not 0 < self.accel <= 1:
                problems.append(f"accel must be in (0, 1], got {self.accel!r}")
            for name in ("max_turn_deg", "start_heading_deg", "crash_penalty"):
                if getattr(self, name) < 0:
                    problems.append(f"{name} must be >= 0, got {getattr(self, name)!r}")
            if self.crash_penalty > 3.4028234663852886e38:
                problems.append(f"crash_penalty must fit the float32 reward (at most 3.4e38), got {self.crash_penalty!r}")
        if problems:
            raise ValueError("Invalid RacingConfig: " + "; ".join(problems))

    @classmethod
    def from_keywords(cls, owner: str, **keywords) -> "RacingConfig":
        """Build from keyword arguments, naming the valid ones if a keyword is unknown."""
        unknown = sorted(set(keywords) - set(cls.__dataclass_fields__))
        if unknown:  # Python's own words first: wrappers (TorchRL's GymEnv: frameskip) recognise and drop such keywords
            raise TypeError(f"{owner} got an unexpected keyword argument {unknown[0]!r}: unknown keyword(s) {unknown}; "
                            f"valid RacingConfig fields: {', '.join(cls.__dataclass_fields__)}")
        return cls(**keywords)

    @property
    def num_rays(self) -> int:
        return len(self.ray_angles_deg)

    @property
    def obs_size(self) -> int:
        """Ray readings followed by the normalised speed."""
        return self.num_rays + 1


PAPER_TRACK_SEEDS: tuple[int, ...] = (2067791, 5468063, 5412436, 8273186, 773203)
"""The five track seeds of the paper's experiments (its Figure 1)."""
