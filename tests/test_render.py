"""Rendering works without a screen and draws what it should."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from racing import RacingEnv
from racing.render import CAR, GRASS, RAY

pytest.importorskip("pygame", reason="rendering needs pygame (pip install -c constraints/cpu.txt -e '.[render]')")

ROOT = Path(__file__).resolve().parents[1]


def _has_colour(frame, colour):
    return bool((frame == np.array(colour, dtype=np.uint8)).all(axis=-1).any())


def test_rgb_array_frame_shows_track_car_and_rays():
    env = RacingEnv(track_seed=2067791, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(10):
        env.step(np.array([1.0, 0.0]))
    frame = env.render()
    assert frame.shape == (600, 600, 3) and frame.dtype == np.uint8
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 5  # not blank
    for colour in (GRASS, CAR, RAY):
        assert _has_colour(frame, colour), colour
    env.close()


def test_frames_follow_the_car():
    env = RacingEnv(track_seed=2067791, render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    for _ in range(30):
        env.step(np.array([1.0, 0.0]))
    assert not np.array_equal(first, env.render())


def test_human_mode_runs_headless():
    env = RacingEnv(track_seed=2067791, render_mode="human")
    env.metadata = {**env.metadata, "render_fps": 1000}
    env.reset(seed=0)
    assert env.step(np.zeros(2))[0].shape == (6,)
    assert env.render() is None
    env.close()


def test_render_without_mode_warns():
    env = RacingEnv(track_seed=1)
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="without a render_mode"):
        assert env.render() is None


def test_paper_tracks_figure(tmp_path):
    pytest.importorskip("matplotlib")
    from racing.figures import tracks_figure

    path = tracks_figure(tmp_path / "tracks.png")
    assert path.stat().st_size > 10_000


def test_demo_writes_its_pictures(tmp_path):
    result = subprocess.run([sys.executable, str(ROOT / "demo.py"), "--out", str(tmp_path)],
                            capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "return" in result.stdout
    for name in ("trajectory.png", "car.png", "paper_tracks.png"):
        assert (tmp_path / name).stat().st_size > 5_000


def test_film_frames_name_the_agent_its_reward_and_show_the_whole_track():
    """Each frame of a film carries the agent's name, its reward so far, and a map of the whole
    track (lower right corner) with the car as a red dot where the car is."""
    from benchmark.protocol import load_agent, run_episode
    from racing.render import MAP_SIZE
    from racing.track_file import example

    env = RacingEnv(render_mode="rgb_array", track_file=str(example("kidney")), max_steps=40)
    frames: list = []
    total = run_episode(load_agent("ray_follower"), env, 0, frames)
    assert env.unwrapped.render_lines == ["ray_follower", f"reward so far {total:.1f}"]
    corner = frames[-1][-MAP_SIZE - 8:-8, -MAP_SIZE - 8:-8]
    red = np.argwhere((corner == CAR).all(axis=-1))
    assert len(red) > 0  # the car's dot on the map
    first_red = np.argwhere((frames[0][-MAP_SIZE - 8:-8, -MAP_SIZE - 8:-8] == CAR).all(axis=-1))
    assert not np.array_equal(red.mean(0), first_red.mean(0))  # the dot moved with the car
