"""``RacingSim``: N cars, each on its own track, stepped together.

This class owns the cars' state, their tracks and their random streams; the Gymnasium env
(one car) and the TorchRL env (N cars) are thin adapters over it.

Random streams follow the reference simulator. Car ``i`` has its own
``numpy.random.RandomState``. A freshly seeded stream first lays out a track
(``num_segments`` draws), as the reference did when it was constructed; each reset then
draws the start state (3 draws). Which track the car drives on is, in order of precedence:
a per-reset override, the car's fixed ``track_seed``, or (``track_seed=None``) the track its
stream lays out anew at every reset. So ``RandomState(S)`` on the track of seed ``S``
reproduces the reference exactly.
"""

from __future__ import annotations

import functools
import weakref
from collections.abc import Sequence

import numpy as np

from racing.config import RacingConfig
from racing.physics import (CarTables, TrackTables, build_tables, car_tables, crosses_segment, inside_parity,
                            ray_distances, ray_distances_car, step_car)
from racing.track import Track, deg_to_rad, layout_track, track_from_seed


@functools.lru_cache(maxsize=256)
def cached_track(seed: int, config: RacingConfig) -> Track:
    """The track of ``seed`` (cached: tracks are immutable)."""
    return track_from_seed(seed, config)


_TABLES: weakref.WeakKeyDictionary[Track, TrackTables] = weakref.WeakKeyDictionary()


def tables_of(track: Track, config: RacingConfig) -> TrackTables:
    tables = _TABLES.get(track)
    if tables is None:
        tables = _TABLES[track] = build_tables(track, config)
    return tables


_CAR_TABLES: weakref.WeakKeyDictionary[Track, CarTables] = weakref.WeakKeyDictionary()


def car_tables_of(track: Track, config: RacingConfig) -> CarTables:
    tables = _CAR_TABLES.get(track)
    if tables is None:
        tables = _CAR_TABLES[track] = car_tables(tables_of(track, config))
    return tables


def check_seed(seed, what: str = "seed") -> int:
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"{what} must be an integer in [0, 2**32), got {seed!r}")
    if not 0 <= int(seed) < 2**32:
        raise ValueError(f"{what} must be in [0, 2**32) (a numpy RandomState seed), got {seed}")
    return int(seed)


class TrackBank:
    """Tables of the tracks in use, side by side: a car's rows are ``slot * N + checkpoint``."""

    def __init__(self, config: RacingConfig):
        self.config = config
        self.tracks: list[Track | None] = []
        self.users: list[int] = []
        self.slot_of: dict[int, int] = {}
        self.edges = np.zeros((7, 2, 4, 0))
        self.respawn = np.zeros((4, 0))
        self.finish = np.zeros((4, 0))
        self.rays = np.zeros((4, 1, 0))

    def acquire(self, track: Track) -> int:
        slot = self.slot_of.get(id(track))
        if slot is None:
            slot = self._store(track)
        self.users[slot] += 1
        return slot

    def release(self, slot: int) -> None:
        self.users[slot] -= 1
        if self.users[slot] == 0:
            del self.slot_of[id(self.tracks[slot])]
            self.tracks[slot] = None

    def _store(self, track: Track) -> int:
        tables = tables_of(track, self.config)
        if None in self.tracks:
            slot = self.tracks.index(None)
        else:
            slot = len(self.tracks)
            self.tracks.append(None)
            self.users.append(0)
            if slot >= self.finish.shape[-1]:
                self._grow(2 * slot + 1)
        if tables.width > self.rays.shape[1]:
            more = tables.width - self.rays.shape[1]
            self.rays = np.concatenate([self.rays, np.full((4, more, self.rays.shape[2]), np.nan)], axis=1)
        n = self.config.num_segments
        rows = slice(slot * n, (slot + 1) * n)
        self.edges[..., rows] = tables.edges
        self.respawn[:, rows] = tables.respawn
        self.finish[:, slot] = tables.finish
        self.rays[:, :, rows] = np.nan
        self.rays[:, : tables.width, rows] = tables.rays
        self.tracks[slot] = track
        self.slot_of[id(track)] = slot
        return slot

    def _grow(self, capacity: int) -> None:
        def grow(a: np.ndarray, size: int) -> np.ndarray:
            return np.concatenate([a, np.zeros(a.shape[:-1] + (size - a.shape[-1],))], axis=-1)

        n = self.config.num_segments
        self.edges = grow(self.edges, capacity * n)
        self.respawn = grow(self.respawn, capacity * n)
        self.rays = grow(self.rays, capacity * n)
        self.finish = grow(self.finish, capacity)


class RacingSim:
    """A batch of cars on race tracks (see the module docstring for the random streams).

    Args:
        num_cars: batch size N.
        track_seeds: one per car, or one for all: an int fixes the car's track, ``None``
            gives it a fresh random track at every reset. ``tracks[i]`` is car i's track:
            a fixed track from construction on, a random one from the car's first reset.
        config: constants of the task.
        nearest_ray: take the nearest ray crossing instead of the reference's first in
            scan order (they differ only where a track crosses itself within sensor range).
        track: one track for every car instead of seeds (a file's: ``racing.track_file``);
            ``config.num_segments`` must be its number of checkpoints. Its resets draw only
            the start state. On a closed track (a circuit) a car that enters checkpoint 0
            from the last completes a lap; ``laps`` and ``lap_times`` (steps) count them, and
            ``config.laps`` > 0 ends (terminates) the car's episode at that many laps.
    """

    CHUNK = 1024  # cars per block of the ray computation (see observe)

    def __init__(self, num_cars: int = 1, track_seeds: int | None | Sequence[int | None] = None,
                 config: RacingConfig = RacingConfig(), nearest_ray: bool = False, track: Track | None = None):
        if isinstance(num_cars, bool) or not isinstance(num_cars, (int, np.integer)) or num_cars < 1:
            raise ValueError(f"num_cars must be a positive integer, got {num_cars!r}")
        if not isinstance(config, RacingConfig):
            raise TypeError(f"config must be a RacingConfig, got {type(config).__name__}")
        self.num_cars = n = int(num_cars)
        self.config = config
        self.nearest_ray = bool(nearest_ray)
        if track_seeds is None or isinstance(track_seeds, (int, np.integer)):
            track_seeds = [track_seeds] * n
        track_seeds = list(track_seeds)
        if len(track_seeds) != n:
            raise ValueError(f"got {len(track_seeds)} track seeds for {n} cars")
        self.track_seeds = [None if s is None else check_seed(s, "track seed") for s in track_seeds]
        if track is not None:
            if any(s is not None for s in self.track_seeds):
                raise ValueError("give a track or track seeds, not both")
            if track.num_checkpoints != config.num_segments:
                raise ValueError(f"the track has {track.num_checkpoints} checkpoints but config.num_segments is "
                                 f"{config.num_segments} (racing.track_file.track_config sets it)")
        if config.laps and (track is None or not track.closed):
            raise ValueError(f"laps={config.laps} ends an episode after laps of a circuit; these cars drive "
                             f"{'an open track' if track is not None else 'generated tracks, which are open'}")
        self.file_track = track
        self.bank = TrackBank(config)
        self.tracks: list[Track | None] = [None] * n
        self.slot = np.zeros(n, dtype=np.int64)
        self.x = np.zeros(n)
        self.y = np.zeros(n)
        self.theta = np.zeros(n)
        self.speed = np.zeros(n)
        self.checkpoint = np.zeros(n, dtype=np.int64)
        self.t = np.zeros(n, dtype=np.int64)
        self.finished = np.zeros(n, dtype=bool)
        self.laps = np.zeros(n, dtype=np.int64)  # laps completed this episode (closed tracks)
        self.lap_start = np.zeros(n, dtype=np.int64)  # the step the current lap began at
        self.crashes = np.zeros(n, dtype=np.int64)  # steps that left the track this episode
        self.lap_times: list[list[int]] = [[] for _ in range(n)]  # steps of each lap completed this episode
        self._streams: list[np.random.RandomState | None] = [None] * n
        self._fresh = [True] * n
        self._reset_once = np.zeros(n, dtype=bool)  # step() needs every car reset at least once
        self._ready = False
        for car, seed in enumerate(self.track_seeds):  # a fixed track is known before any reset
            if seed is not None:
                self._use_track(car, cached_track(seed, config))
            elif track is not None:
                self._use_track(car, track)

    # ----------------------------------------------------------------------------- seeding
    def seed(self, seeds: int | Sequence[int], cars: Sequence[int] | None = None) -> None:
        """Re-seed the cars' streams: one seed each, or ``seed + k`` for the k-th car given."""
        cars = range(self.num_cars) if cars is None else list(cars)
        if not isinstance(seeds, (Sequence, np.ndarray)):
            base = check_seed(seeds)
            seeds = [(base + k) % 2**32 for k in range(len(cars))]
        seeds = [check_seed(s) for s in seeds]
        if len(seeds) != len(cars):
            raise ValueError(f"got {len(seeds)} seeds for {len(cars)} cars")
        for car, s in zip(cars, seeds):
            self._streams[car] = np.random.RandomState(s)
            self._fresh[car] = True

    CAR_STATE = ("x", "y", "theta", "speed", "checkpoint", "t", "finished", "_reset_once", "laps", "lap_start",
                 "crashes")
    STEP_SECONDS = 1 / 30  # a step is one frame of the game, shown at 30 frames per second (lap times in seconds)

    def state_dict(self) -> dict:
        """Everything that decides what the cars do next, as plain NumPy arrays.

        Car states, their random streams and their current tracks (a fixed track by its seed,
        a random one by its walls). ``load_state_dict`` on a simulator built with the same
        arguments continues exactly from here, mid-episode or between episodes.
        """
        n = self.num_cars
        seeded = np.array([s is not None for s in self._streams])
        keys = np.zeros((n, 624), dtype=np.uint32)
        pos, has_gauss, gauss = np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n)
        for car, stream in enumerate(self._streams):
            if stream is not None:
                _, keys[car], pos[car], has_gauss[car], gauss[car] = stream.get_state()
        walls = np.full((n, 2, self.config.num_segments + 1, 2), np.nan)
        track_seed = np.full(n, -1, dtype=np.int64)
        for car, track in enumerate(self.tracks):
            if track is not None:
                walls[car] = track.left_wall, track.right_wall
                track_seed[car] = -1 if track.seed is None else track.seed
        laps = max([len(times) for times in self.lap_times] + [1])
        lap_times = np.full((n, laps), -1, dtype=np.int64)
        for car, times in enumerate(self.lap_times):
            lap_times[car, : len(times)] = times
        return {"seeded": seeded, "keys": keys, "pos": pos, "has_gauss": has_gauss, "gauss": gauss,
                "fresh": np.array(self._fresh), "track_seed": track_seed, "walls": walls, "lap_times": lap_times,
                **{name: getattr(self, name).copy() for name in self.CAR_STATE}}

    def load_state_dict(self, state: dict) -> None:
        """Continue from a ``state_dict()`` of a simulator with the same number of cars and config."""
        n = self.num_cars
        seeded = np.asarray(state["seeded"], dtype=bool)
        if seeded.shape != (n,) or np.shape(state["walls"])[2] != self.config.num_segments + 1:
            raise ValueError(f"a simulator state of {seeded.shape[0]} cars on tracks of "
                             f"{np.shape(state['walls'])[2] - 1} checkpoints does not fit this simulator "
                             f"({n} cars, {self.config.num_segments} checkpoints)")
        for car in range(n):
            stream = None
            if seeded[car]:
                stream = np.random.RandomState()
                stream.set_state(("MT19937", np.asarray(state["keys"][car], dtype=np.uint32),
                                  int(state["pos"][car]), int(state["has_gauss"][car]), float(state["gauss"][car])))
            self._streams[car] = stream
            walls, seed = np.asarray(state["walls"][car]), int(state["track_seed"][car])
            if seed >= 0:
                self._use_track(car, cached_track(seed, self.config))
            elif self.file_track is not None:
                if not (np.array_equal(walls[0], self.file_track.left_wall)
                        and np.array_equal(walls[1], self.file_track.right_wall)):
                    raise ValueError("the simulator state was taken on another track than this simulator's")
            elif not np.isnan(walls).all():
                self._use_track(car, Track(walls[0], walls[1]))
        self._fresh = [bool(f) for f in state["fresh"]]
        for name in self.CAR_STATE:
            current = getattr(self, name)
            if name not in state:  # a state from before laps and crashes were counted
                setattr(self, name, np.zeros_like(current))
                continue
            setattr(self, name, np.asarray(state[name], dtype=current.dtype).reshape(current.shape).copy())
        lap_times = np.asarray(state.get("lap_times", np.full((n, 1), -1)))
        self.lap_times = [[int(v) for v in row if v >= 0] for row in lap_times]
        self._ready = bool(self._reset_once.all())

    def _stream(self, car: int) -> np.random.RandomState:
        stream = self._streams[car]
        if stream is None:  # never seeded: a fixed track's own seed (as the reference), else entropy
            seed = self.track_seeds[car]
            if seed is None:
                seed = int(np.random.SeedSequence().generate_state(1)[0])
            stream = self._streams[car] = np.random.RandomState(seed)
            self._fresh[car] = True
        return stream

    # ------------------------------------------------------------------------------- reset
    def reset(self, cars: Sequence[int] | np.ndarray | None = None,
              track_seed: int | None = None) -> None:
        """Put the given cars (default: all) at the start of their tracks.

        ``track_seed`` overrides the track of these cars for this episode only.
        """
        cfg = self.config
        cars = range(self.num_cars) if cars is None else np.asarray(cars, dtype=np.int64).ravel()
        if track_seed is not None and self.file_track is not None:
            raise ValueError("a simulator on a given track (a file's) takes no track_seed at reset")
        override = None if track_seed is None else cached_track(check_seed(track_seed, "track_seed"), cfg)
        for car in cars:
            car = int(car)
            stream = self._stream(car)
            fixed = self.track_seeds[car]
            track = None
            if self.file_track is not None:  # no layout draws: only the start state
                self._fresh[car] = False
                track = self.file_track
            elif self._fresh[car] or fixed is None:
                if fixed is None and override is None:
                    track = layout_track(stream, cfg)
                else:  # the stream lays out a track that is not used: draw and drop it
                    stream.random_sample(cfg.num_segments)
                self._fresh[car] = False
            track = override or track or cached_track(fixed, cfg)
            self._use_track(car, track)
            u = stream.random_sample(3)
            self.x[car] = u[0] - 0.5
            self.y[car] = u[1] - 0.5
            self.theta[car] = deg_to_rad((u[2] - 0.5) * cfg.start_heading_deg)
        self.speed[cars] = 0.0
        self.checkpoint[cars] = 0
        self.t[cars] = 0
        self.finished[cars] = False
        self.laps[cars] = 0
        self.lap_start[cars] = 0
        self.crashes[cars] = 0
        for car in cars:
            self.lap_times[int(car)] = []
        if not self._ready:
            self._reset_once[cars] = True
            self._ready = bool(self._reset_once.all())

    def _use_track(self, car: int, track: Track) -> None:
        if self.tracks[car] is track:
            return
        if self.tracks[car] is not None:
            self.bank.release(int(self.slot[car]))
        self.slot[car] = self.bank.acquire(track)
        self.tracks[car] = track
        if self.num_cars == 1:
            self._car = car_tables_of(track, self.config)

    # -------------------------------------------------------------------------------- step
    def step(self, throttle: np.ndarray, steer: np.ndarray):
        """Advance every car one frame. Actions are float64 arrays of shape (N,), clipped to [-1, 1].

        Returns ``(reward, terminated, truncated, crashed)``, each of shape (N,).
        """
        cfg = self.config
        if not self._ready:
            cars = np.flatnonzero(~self._reset_once)
            raise RuntimeError(f"RacingSim.step() called before reset() of cars {cars[:8].tolist()}")
        if self.num_cars == 1:
            return tuple(np.array([value]) for value in self.step_car(float(throttle[0]), float(steer[0])))
        throttle = np.minimum(np.maximum(throttle, -1.0), 1.0)
        steer = np.minimum(np.maximum(steer, -1.0), 1.0)
        speed = self.speed + ((throttle / 2 + 0.5) * cfg.max_speed - self.speed) * cfg.accel
        theta = self.theta - steer * speed / np.maximum(speed**2 / cfg.turn_rate, cfg.min_turn_radius)
        old_x, old_y = self.x, self.y
        x = old_x + np.sin(theta) * speed
        y = old_y + np.cos(theta) * speed
        reward = speed / cfg.max_speed

        rows = self.slot * cfg.num_segments + self.checkpoint
        in_current, in_next = inside_parity(x, y, self.bank.edges.take(rows, axis=-1))
        advanced = ~in_current & in_next
        off_track = ~(in_current | in_next)
        finished = np.zeros(self.num_cars, dtype=bool)
        if off_track.any():
            last = off_track & (self.checkpoint == cfg.num_segments - 1)
            if last.any():
                f = self.bank.finish[:, self.slot[last]]
                finished[last] = crosses_segment(*f, old_x[last], old_y[last], x[last], y[last])
                off_track &= ~finished
            if off_track.any():
                back = self.bank.respawn[:, rows[off_track]]
                reward[off_track] -= cfg.crash_penalty
                self.checkpoint[off_track] = back[0].astype(np.int64)
                x[off_track], y[off_track], theta[off_track] = back[1], back[2], back[3]
                speed[off_track] = 0.0
        self.checkpoint += advanced
        self.x, self.y, self.theta, self.speed = x, y, theta, speed
        self.t += 1
        self.crashes += off_track
        lapped = self.checkpoint == cfg.num_segments  # only on a circuit: checkpoint 0 follows the last
        if lapped.any():
            for car in np.flatnonzero(lapped).tolist():
                finished[car] = self._lap(car)
        self.finished = finished
        return reward, finished, self.t >= cfg.max_steps, off_track

    def _lap(self, car: int) -> bool:
        """Car ``car`` has just entered checkpoint 0 from the last one of a circuit: whether that
        ends its episode (``config.laps``)."""
        self.checkpoint[car] = 0
        self.laps[car] += 1
        self.lap_times[car].append(int(self.t[car] - self.lap_start[car]))
        self.lap_start[car] = self.t[car]
        return 0 < self.config.laps <= self.laps[car]

    def step_car(self, throttle: float, steer: float) -> tuple[float, bool, bool, bool]:
        """``step`` of a one-car simulator with Python scalars in and out (``physics.step_car``:
        the same arithmetic without NumPy's per-call cost). Returns ``(reward, terminated,
        truncated, crashed)``."""
        if self.num_cars != 1:
            raise ValueError(f"step_car() steps a one-car simulator; this one has {self.num_cars} cars")
        if not self._ready:
            raise RuntimeError("RacingSim.step_car() called before reset()")
        cfg = self.config
        (x, y, theta, speed, checkpoint, reward, finished, crashed) = step_car(
            float(self.x[0]), float(self.y[0]), float(self.theta[0]), float(self.speed[0]), int(self.checkpoint[0]),
            throttle, steer, self._car, cfg)
        self.x[0], self.y[0], self.theta[0], self.speed[0], self.checkpoint[0] = x, y, theta, speed, checkpoint
        self.t[0] += 1
        self.crashes[0] += crashed
        if checkpoint == cfg.num_segments:  # only on a circuit
            finished = self._lap(0)
        self.finished[0] = finished
        return reward, finished, bool(self.t[0] >= cfg.max_steps), crashed

    # ---------------------------------------------------------------------------- observe
    def observe(self) -> np.ndarray:
        """Ray readings (divided by the ray length) and speed / max_speed: (N, num_rays + 1) float64."""
        if self.num_cars == 1:
            return np.array([self.observe_car()])
        cfg = self.config
        rows = self.slot * cfg.num_segments + self.checkpoint
        obs = np.empty((cfg.obs_size, self.num_cars))
        # In chunks of cars: the temporaries stay in cache and off the page-faulting allocator.
        for start in range(0, self.num_cars, self.CHUNK):
            cars = slice(start, start + self.CHUNK)
            rays = self.bank.rays.take(rows[cars], axis=-1)
            obs[:-1, cars] = ray_distances(self.x[cars], self.y[cars], self.theta[cars], rays,
                                           cfg, self.nearest_ray)
        obs[:-1] /= cfg.ray_length
        obs[-1] = self.speed / cfg.max_speed
        return obs.T

    def observe_car(self) -> list[float]:
        """``observe`` of a one-car simulator, as a list of Python floats."""
        cfg = self.config
        x, y, theta = float(self.x[0]), float(self.y[0]), float(self.theta[0])
        readings = ray_distances_car(x, y, theta, self._car.segments[int(self.checkpoint[0])], cfg, self.nearest_ray)
        return [r / cfg.ray_length for r in readings] + [float(self.speed[0]) / cfg.max_speed]

    TRUE_STATE = ("progress", "lateral", "heading_cos", "heading_sin")  # the columns of true_state()

    def true_state(self) -> np.ndarray:
        """Each car's true state in its track's frame, (N, 4) float64 (what no ray shows; for a critic
        that trains on it, ``algo.td.privileged_critic``): its progress along the track (checkpoint plus
        the fraction of the centre line's segment through it, over the number of checkpoints), its signed
        offset from that segment (positive counter-clockwise of its direction in the x-y plane) over the half width, and the cosine and sine of
        its heading relative to the segment's direction. The centre line joins the midpoints of the
        walls' points; only +, -, x, /, sqrt and the physics' own sine and cosine: the same bits on every CPU."""
        cfg = self.config
        if getattr(self, "_centre_tracks", None) is None or len(self._centre_tracks) != self.num_cars:
            self._centre_tracks = [None] * self.num_cars
            self._centres = np.zeros((self.num_cars, cfg.num_segments + 1, 2))
        for car, track in enumerate(self.tracks):  # a car's centre line, rebuilt when its track changes
            if track is not self._centre_tracks[car]:
                self._centre_tracks[car] = track
                if track is not None:
                    self._centres[car] = (track.left_wall + track.right_wall) / 2.0
        cars = np.arange(self.num_cars)
        i = np.minimum(self.checkpoint, cfg.num_segments - 1)
        a, b = self._centres[cars, i], self._centres[cars, i + 1]
        seg = b - a
        length = np.sqrt(seg[:, 0] * seg[:, 0] + seg[:, 1] * seg[:, 1])
        ux, uy = seg[:, 0] / length, seg[:, 1] / length
        rx, ry = self.x - a[:, 0], self.y - a[:, 1]
        along = np.clip((rx * ux + ry * uy) / length, 0.0, 1.0)
        hx, hy = np.sin(self.theta), np.cos(self.theta)  # the direction the car moves in (racing.physics)
        return np.stack([(i + along) / cfg.num_segments, (ux * ry - uy * rx) / cfg.half_width,
                         ux * hx + uy * hy, ux * hy - uy * hx], axis=1)

    def car_state(self, car: int = 0) -> dict:
        """The state of one car as plain Python values."""
        track = self.tracks[car]
        n = self.config.num_segments
        state = {
            "x": float(self.x[car]), "y": float(self.y[car]), "theta": float(self.theta[car]),
            "speed": float(self.speed[car]), "checkpoint": int(self.checkpoint[car]),
            "step": int(self.t[car]), "track_seed": None if track is None else track.seed,
            "progress": (int(self.checkpoint[car]) + bool(self.finished[car])) / n,
            "crashes": int(self.crashes[car]),
        }
        if track is not None and track.closed:  # progress: the fraction of the current lap
            state["laps"] = int(self.laps[car])
            state["lap_times"] = list(self.lap_times[car])  # steps
            state["lap_seconds"] = [round(steps * self.STEP_SECONDS, 6) for steps in self.lap_times[car]]
        return state
