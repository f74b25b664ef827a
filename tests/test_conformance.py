"""The simulator against the reference vectors of the five paper tracks (docs/specification.md).

Every implementation is checked: the batched engine (all rollouts of a track as one
batch), both environments, and the plain-Python benchmark baseline.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from speed.scalar_racing import ScalarRacing
from racing import PAPER_TRACK_SEEDS, RacingEnv, RacingSim, RacingTorchEnv, track_from_seed

STATE_TOL, OBS_TOL = 1e-9, 1e-6
STATE_KEYS = ("x", "y", "theta", "speed")


def _track(conformance, seed):
    (track,) = [t for t in conformance["tracks"] if t["seed"] == seed]
    return track


def _check_step(where, got_state, got_obs, got_reward, expected, reward_tol=STATE_TOL):
    for key in STATE_KEYS:
        assert got_state[key] == pytest.approx(expected[key], abs=STATE_TOL), f"{where}: {key}"
    assert got_state["checkpoint"] == expected["checkpoint"], f"{where}: checkpoint"
    assert got_reward == pytest.approx(expected["reward"], abs=reward_tol), f"{where}: reward"
    np.testing.assert_allclose(got_obs, expected["obs"], atol=OBS_TOL, rtol=0, err_msg=f"{where}: obs")


def test_the_vectors_cover_the_five_paper_tracks(conformance):
    assert sorted(t["seed"] for t in conformance["tracks"]) == sorted(PAPER_TRACK_SEEDS)


@pytest.mark.parametrize("seed", PAPER_TRACK_SEEDS)
def test_walls(conformance, seed):
    expected = _track(conformance, seed)
    track = track_from_seed(seed)
    np.testing.assert_allclose(track.left_wall, expected["left_wall"], atol=1e-12, rtol=0)
    np.testing.assert_allclose(track.right_wall, expected["right_wall"], atol=1e-12, rtol=0)
    assert track.left_wall.shape == (51, 2)


@pytest.mark.parametrize("seed", PAPER_TRACK_SEEDS)
def test_batched_engine_reproduces_every_rollout(conformance, seed):
    expected = _track(conformance, seed)
    rollouts = expected["rollouts"]
    sim = RacingSim(len(rollouts), seed)
    sim.reset()
    start = expected["start"]
    for car in range(len(rollouts)):
        state = sim.car_state(car)
        for key in ("x", "y", "theta"):
            assert state[key] == pytest.approx(start[key], abs=STATE_TOL)
        np.testing.assert_allclose(sim.observe()[car], start["obs"], atol=OBS_TOL, rtol=0)
    actions = np.array([r["actions"] for r in rollouts])  # (cars, steps, 2)
    for k in range(actions.shape[1]):
        reward, terminated, truncated, _ = sim.step(actions[:, k, 0], actions[:, k, 1])
        obs = sim.observe()
        for car, rollout in enumerate(rollouts):
            _check_step(f"{rollout['name']} step {k}", sim.car_state(car), obs[car], reward[car],
                        rollout["steps"][k])
        assert not terminated.any()
        assert truncated.all() == (k == actions.shape[1] - 1)


@pytest.mark.parametrize("seed", PAPER_TRACK_SEEDS)
def test_gymnasium_env_reproduces_every_rollout(conformance, seed):
    expected = _track(conformance, seed)
    env = RacingEnv(track_seed=seed)
    for rollout in expected["rollouts"]:
        obs, _ = env.reset(seed=seed)  # a seeded stream lays out the track, then the start state
        np.testing.assert_allclose(obs, expected["start"]["obs"], atol=OBS_TOL, rtol=0)
        for k, (action, step) in enumerate(zip(rollout["actions"], rollout["steps"])):
            obs, reward, terminated, truncated, info = env.step(np.array(action, dtype=np.float32))
            _check_step(f"{rollout['name']} step {k}", info, obs, reward, step)
        assert truncated and not terminated


@pytest.mark.parametrize("seed", PAPER_TRACK_SEEDS[:2])
def test_torchrl_env_reproduces_every_rollout(conformance, seed):
    expected = _track(conformance, seed)
    rollouts = expected["rollouts"]
    env = RacingTorchEnv(num_envs=len(rollouts), track_seeds=seed)
    env.set_seed(seed)
    env.sim.seed([seed] * len(rollouts))  # every car replays the reference stream
    td = env.reset()
    actions = torch.tensor([r["actions"] for r in rollouts], dtype=torch.float32)
    for k in range(actions.shape[1]):
        td["action"] = actions[:, k]
        td = env.step(td)["next"]
        for car, rollout in enumerate(rollouts):
            _check_step(f"{rollout['name']} step {k}", env.sim.car_state(car),
                        td["observation"][car].numpy(), float(td["reward"][car]), rollout["steps"][k],
                        reward_tol=OBS_TOL)  # the TorchRL reward is float32


@pytest.mark.parametrize("seed", PAPER_TRACK_SEEDS)
@pytest.mark.parametrize("nearest", [False, True])
def test_scalar_baseline_reproduces_every_rollout(conformance, seed, nearest):
    expected = _track(conformance, seed)
    for rollout in expected["rollouts"]:
        car = ScalarRacing(seed, nearest=nearest)
        obs = car.reset()
        np.testing.assert_allclose(obs, expected["start"]["obs"], atol=OBS_TOL, rtol=0)
        for k, (action, step) in enumerate(zip(rollout["actions"], rollout["steps"])):
            obs, reward, _, _ = car.step(*action)
            state = {"x": car.x, "y": car.y, "theta": car.theta, "speed": car.speed,
                     "checkpoint": car.checkpoint}
            _check_step(f"{rollout['name']} step {k}", state, obs, reward, step)
