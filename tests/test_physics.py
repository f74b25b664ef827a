"""Properties of the batched physics: exact culling, polygon tests, ray rules, validation."""

from __future__ import annotations

import numpy as np
import pytest

from speed.scalar_racing import _inside
from racing import RacingConfig, RacingSim, track_from_seed
from racing.physics import build_tables, crosses_segment, inside_parity, ray_distances

CONFIG = RacingConfig()


def _unculled_rays(track, c):
    """Every wall segment from checkpoint c on, in scan order: the table without culling."""
    n = track.num_checkpoints
    segments = [(wall[i], wall[i + 1]) for i in range(c, n) for wall in (track.left_wall, track.right_wall)]
    p1 = np.array([a for a, _ in segments]).T
    v2 = np.array([b - a for a, b in segments]).T
    return np.concatenate([p1, v2])  # (4, W)


def _points_in_checkpoint(track, c, rng, k):
    corners = track.checkpoint(c)
    weights = rng.dirichlet(np.ones(4), size=k)
    return weights @ corners  # convex combinations: inside the corners' hull


@pytest.mark.parametrize("seed", [2067791, 773203, 1, 2, 3, 4, 5, 6, 7, 8])
@pytest.mark.parametrize("nearest", [False, True])
def test_culling_never_changes_a_reading(seed, nearest):
    track = track_from_seed(seed)
    tables = build_tables(track, CONFIG)
    assert tables.width < 2 * track.num_checkpoints  # culling removes most segments
    rng = np.random.default_rng(seed)
    for c in range(track.num_checkpoints):
        points = _points_in_checkpoint(track, c, rng, 16)
        x, y = points[:, 0], points[:, 1]
        theta = rng.uniform(-np.pi, np.pi, len(x))
        culled = np.repeat(tables.rays[:, :, c:c + 1], len(x), axis=2)
        full = np.repeat(_unculled_rays(track, c)[:, :, None], len(x), axis=2)
        np.testing.assert_array_equal(ray_distances(x, y, theta, culled, CONFIG, nearest),
                                      ray_distances(x, y, theta, full, CONFIG, nearest))


def test_first_and_nearest_crossing_differ_only_on_self_crossing_tracks():
    """The reference reads the first crossing in scan order; a track that loops back under a ray
    can hide a nearer wall further down the scan. Find such a case among random tracks."""
    differ = 0
    for seed in range(40):
        sim_first, sim_near = RacingSim(64, seed), RacingSim(64, seed, nearest_ray=True)
        for sim in (sim_first, sim_near):
            sim.seed(0)
            sim.reset()
        rng = np.random.default_rng(seed)
        for _ in range(100):
            a = rng.uniform(-1, 1, (2, 64))
            a[0] = 0.6
            for sim in (sim_first, sim_near):
                sim.step(a[0], a[1])
            first, near = sim_first.observe(), sim_near.observe()
            assert (near <= first).all()  # the nearest is never farther than the first
            differ += int((near < first).any())
    assert differ > 0


@pytest.mark.parametrize("nearest", [False, True])
@pytest.mark.parametrize("track_seed, options", [(None, {}), (None, {"num_segments": 6}), (2067791, {})])
def test_one_car_path_equals_the_batched_path(nearest, track_seed, options):
    """A one-car simulator takes the scalar path (physics.step_car); car 0 of a two-car
    simulator the batched one. Same streams, same actions: identical to the bit, over random
    tracks (self-crossing ones among them), crashes, respawns and, on 6-segment tracks, finishes."""
    config = RacingConfig(**options)
    one, two = RacingSim(1, track_seed, config, nearest), RacingSim(2, track_seed, config, nearest)
    one.seed([11])
    two.seed([11, 12])
    rng = np.random.default_rng(0)
    events = {"crashed": 0, "finished": 0}
    for episode in range(30):
        one.reset()
        two.reset()
        for _ in range(120):
            a = rng.uniform(-1.3, 1.3, 2)
            a[0] = max(a[0], rng.uniform(0.2, 1.0))  # mostly forward, so cars get somewhere
            solo = one.step(a[:1], a[1:])
            pair = two.step(np.array([a[0], 0.0]), np.array([a[1], 0.0]))
            for mine, theirs in zip(solo, pair):
                assert mine[0] == theirs[0]
            np.testing.assert_array_equal(one.observe()[0], two.observe()[0])
            for name in ("x", "y", "theta", "speed", "checkpoint", "t"):
                assert getattr(one, name)[0] == getattr(two, name)[0], name
            events["crashed"] += int(solo[3][0])
            events["finished"] += int(solo[1][0])
            if solo[1][0] or solo[2][0]:
                break
    assert events["crashed"] > 0
    assert events["finished"] > 0 or options.get("num_segments") != 6


def test_inside_parity_matches_the_scalar_polygon_test():
    rng = np.random.default_rng(0)
    track = track_from_seed(5468063)
    tables = build_tables(track, CONFIG)
    for c in (0, 10, 48, 49):
        points = np.concatenate([_points_in_checkpoint(track, c, rng, 50),
                                 track.centres[c] + rng.normal(0, 150, (200, 2))])
        x, y = points[:, 0], points[:, 1]
        edges = np.repeat(tables.edges[..., c:c + 1], len(x), axis=-1)
        inside_c, inside_next = inside_parity(x, y, edges)
        quad = [tuple(p) for p in track.checkpoint(c)]
        expected = [_inside(px, py, quad) for px, py in points]
        np.testing.assert_array_equal(inside_c, expected)
        if c + 1 < track.num_checkpoints:
            quad = [tuple(p) for p in track.checkpoint(c + 1)]
            np.testing.assert_array_equal(inside_next, [_inside(px, py, quad) for px, py in points])
        else:
            assert not inside_next.any()  # no checkpoint after the last


def test_crossing_a_segment():
    a = np.array
    args = (a([0.0]), a([0.0]), a([10.0]), a([0.0]))  # segment along the x axis
    assert crosses_segment(*args, a([5.0]), a([-1.0]), a([5.0]), a([1.0]))[0]
    assert not crosses_segment(*args, a([5.0]), a([1.0]), a([5.0]), a([2.0]))[0]
    assert not crosses_segment(*args, a([15.0]), a([-1.0]), a([15.0]), a([1.0]))[0]


def test_respawn_faces_along_the_track_at_the_previous_checkpoint():
    sim = RacingSim(1, 2067791)
    sim.seed(0)
    sim.reset()
    for _ in range(60):  # full throttle, hard left: the car leaves the track
        _, _, _, crashed = sim.step(np.array([1.0]), np.array([1.0]))
        if crashed[0]:
            break
    assert crashed[0]
    c = int(sim.checkpoint[0])
    track = sim.tracks[0]
    assert (sim.x[0], sim.y[0]) == tuple(track.centres[c])
    assert sim.speed[0] == 0.0
    assert sim.theta[0] == pytest.approx(track.respawn_heading(c))


def test_track_bank_reuses_slots_of_random_tracks():
    sim = RacingSim(8, None)
    sim.seed(0)
    for _ in range(20):
        sim.reset()
    assert len(sim.bank.tracks) <= 16  # 8 in use, at most 8 more awaiting reuse
    assert len({id(t) for t in sim.tracks}) == 8


@pytest.mark.parametrize("kwargs, message", [
    ({"num_segments": 1}, r"num_segments must be an integer in \[2, 5,000\]"),
    ({"max_speed": -1.0}, "max_speed must be > 0"),
    ({"accel": 1.5}, "accel must be in (0, 1]"),
    ({"ray_length": float("nan")}, "ray_length must be finite"),
    ({"max_steps": 0}, r"max_steps must be an integer in \[1, 1,000,000\]"),
    ({"ray_angles_deg": ()}, "ray_angles_deg must be a non-empty sequence"),
    ({"half_width": "wide"}, "half_width must be a number"),
])
def test_config_rejects_bad_values(kwargs, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        RacingConfig(**kwargs)


def test_bad_seeds_and_sizes_are_refused():
    with pytest.raises(ValueError, match="num_cars must be a positive integer"):
        RacingSim(0)
    with pytest.raises(ValueError, match=r"track seed must be in \[0, 2\*\*32\)"):
        RacingSim(1, -3)
    with pytest.raises(ValueError, match="got 2 track seeds for 3 cars"):
        RacingSim(3, [1, 2])
    with pytest.raises(TypeError, match="seed must be an integer"):
        RacingSim(1, 1).seed(1.5)
    with pytest.raises(RuntimeError, match="before reset"):
        RacingSim(1, 1).step(np.zeros(1), np.zeros(1))
    half = RacingSim(2, 1)
    half.reset([0])
    with pytest.raises(RuntimeError, match=r"before reset\(\) of cars \[1\]"):
        half.step(np.zeros(2), np.zeros(2))
