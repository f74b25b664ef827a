"""The Gymnasium environment: API conformance, seeding, determinism, bad input, episode end."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import racing
from racing import ENV_ID, PAPER_TRACK_SEEDS, RacingEnv, track_from_seed
from racing.driver import ray_follower


def _rollout(env, seed, steps=200, actions_seed=0):
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(actions_seed)
    out = [obs]
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        out.append(np.append(obs, [reward, terminated, truncated]))
    return np.concatenate(out)


@pytest.mark.parametrize("track_seed", [2067791, None])
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_passes_gymnasiums_env_checker(track_seed, render_mode):
    check_env(gym.make(ENV_ID, track_seed=track_seed, render_mode=render_mode).unwrapped)


def test_registered_and_made_with_keywords():
    env = gym.make(ENV_ID, track_seed=2067791, num_segments=20)
    assert isinstance(env.unwrapped, RacingEnv)
    assert env.unwrapped.config.num_segments == 20
    env.reset(seed=1)
    assert env.unwrapped.track.left_wall.shape == (21, 2)
    assert env.unwrapped.track.right_wall.shape == (21, 2)


def test_a_fixed_track_is_there_before_reset_and_a_random_one_after():
    fixed = gym.make(ENV_ID, track_seed=2067791).unwrapped
    np.testing.assert_array_equal(fixed.track.left_wall, track_from_seed(2067791).left_wall)
    before = fixed.track
    fixed.reset(seed=3)
    assert fixed.track is before
    fixed.reset(options={"track_seed": 773203})  # one episode on another track
    np.testing.assert_array_equal(fixed.track.right_wall, track_from_seed(773203).right_wall)
    random = gym.make(ENV_ID, track_seed=None).unwrapped
    assert random.track is None
    random.reset(seed=5)
    assert random.track is not None and random.track.seed is None


def test_spaces_have_the_true_bounds():
    env = RacingEnv()
    assert env.action_space == gym.spaces.Box(-1, 1, (2,), np.float32)
    assert env.observation_space == gym.spaces.Box(0, 1, (6,), np.float32)


def test_same_seed_same_rollout_and_different_seed_different_rollout():
    a = _rollout(RacingEnv(track_seed=5468063), seed=7)
    b = _rollout(RacingEnv(track_seed=5468063), seed=7)
    c = _rollout(RacingEnv(track_seed=5468063), seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_unseeded_fixed_track_starts_like_the_reference():
    """Without a seed, a fixed track's stream is RandomState(track_seed), as in the reference:
    the first reset equals reset(seed=track_seed)."""
    obs, info = RacingEnv(track_seed=773203).reset()
    obs_seeded, info_seeded = RacingEnv(track_seed=773203).reset(seed=773203)
    np.testing.assert_array_equal(obs, obs_seeded)
    assert info == info_seeded


def test_resets_continue_the_stream():
    env = RacingEnv(track_seed=2067791)
    first, _ = env.reset(seed=3)
    second, info = env.reset()
    assert info["step"] == 0 and info["checkpoint"] == 0
    assert not np.array_equal(first, second)  # a new start state from the same stream


def test_random_tracks_follow_the_seed():
    env = RacingEnv(track_seed=None)
    env.reset(seed=5412436)  # a seeded stream lays out its own seed's track first
    np.testing.assert_array_equal(env.track.left_wall, track_from_seed(5412436).left_wall)
    assert env.reset()[1]["track_seed"] is None  # then fresh, unnamed tracks
    assert not np.array_equal(env.track.left_wall, track_from_seed(5412436).left_wall)


def test_track_option_picks_the_track_of_one_episode():
    env = RacingEnv(track_seed=2067791)
    _, info = env.reset(seed=0, options={"track_seed": 8273186})
    assert info["track_seed"] == 8273186
    np.testing.assert_array_equal(env.track.right_wall, track_from_seed(8273186).right_wall)
    assert env.reset()[1]["track_seed"] == 2067791
    with pytest.raises(ValueError, match="unknown reset options \\['track'\\]"):
        env.reset(options={"track": 1})


def test_info_carries_the_car_state():
    env = RacingEnv(track_seed=2067791)
    _, info = env.reset(seed=0)
    assert {"x", "y", "theta", "speed", "checkpoint", "progress", "step", "track_seed",
            "crashed", "finished"} <= set(info)
    _, _, _, _, info = env.step(np.array([1.0, 0.0], np.float32))
    assert info["speed"] == pytest.approx(2.5)  # 5% of the 50 px gap
    assert info["step"] == 1


@pytest.mark.parametrize("action, error, message", [
    (np.array([np.nan, 0.0]), ValueError, "contains NaN or inf"),
    (np.array([0.0, np.inf]), ValueError, "contains NaN or inf"),
    (np.zeros(3), ValueError, r"shape \(3,\), expected \(2,\)"),
    (np.zeros((1, 2)), ValueError, r"shape \(1, 2\), expected \(2,\)"),
    (0.5, ValueError, r"shape \(\), expected \(2,\)"),
    (np.array(["a", "b"]), TypeError, "is not a real number type"),
    (np.array([1 + 1j, 0]), TypeError, "is not a real number type"),
    (np.array([True, False]), TypeError, "is not a real number type"),
    ([[0.1], [0.2, 0.3]], TypeError, "could not read the action"),
])
def test_bad_actions_get_clear_errors(action, error, message):
    env = RacingEnv(track_seed=1)
    env.reset(seed=0)
    with pytest.raises(error, match=message):
        env.step(action)


def test_out_of_range_actions_are_clipped():
    a, b = RacingEnv(track_seed=1), RacingEnv(track_seed=1)
    a.reset(seed=0)
    b.reset(seed=0)
    for _ in range(20):
        out_a = a.step(np.array([3.0, -7.0]))
        out_b = b.step(np.array([1.0, -1.0], np.float32))
        np.testing.assert_array_equal(out_a[0], out_b[0])
        assert out_a[1:4] == out_b[1:4]


def test_integer_and_list_actions_are_accepted():
    env = RacingEnv(track_seed=1)
    env.reset(seed=0)
    env.step([1, 0])
    env.step(np.array([0, -1], dtype=np.int8))


def test_truncated_after_max_steps_not_terminated():
    env = RacingEnv(track_seed=2067791, max_steps=5)
    env.reset(seed=0)
    flags = [env.step(np.zeros(2))[2:4] for _ in range(5)]
    assert flags == [(False, False)] * 4 + [(False, True)]


def test_finishing_the_track_terminates_the_episode():
    env = RacingEnv(track_seed=PAPER_TRACK_SEEDS[0], num_segments=6, max_steps=1000)
    obs, _ = env.reset(seed=0)
    for _ in range(1000):
        obs, _, terminated, truncated, info = env.step(ray_follower(obs))
        if terminated or truncated:
            break
    assert terminated and not truncated
    assert info["finished"] and info["progress"] == 1.0
    assert info["checkpoint"] == 5


def test_leaving_the_track_costs_the_penalty():
    env = RacingEnv(track_seed=2067791)
    env.reset(seed=0)
    for _ in range(100):
        _, reward, _, _, info = env.step(np.array([1.0, 1.0]))
        if info["crashed"]:
            break
    assert info["crashed"]
    assert -10.0 <= reward < -9.0  # speed / max_speed - 10
    assert info["speed"] == 0.0


def test_bad_constructor_arguments():
    with pytest.raises(TypeError, match=r"RacingEnv .* unknown keyword\(s\) \['track_seeed'\]; valid"):
        RacingEnv(track_seeed=3)
    with pytest.raises(ValueError, match="render_mode must be one of"):
        RacingEnv(render_mode="rgb")
    with pytest.raises(ValueError, match="max_speed must be > 0"):
        RacingEnv(max_speed=0)


def test_module_reexports():
    assert racing.RacingTorchEnv.__name__ == "RacingTorchEnv"
    with pytest.raises(AttributeError):
        racing.NoSuchThing  # noqa: B018


def test_a_third_party_scripts_env_stack_runs_through_episode_ends():
    """docs/usage.md's third-party script (CleanRL's continuous-action PPO for Gymnasium 1.x) builds its
    vector env from ``gym.make(env_id)`` and Gymnasium's own wrappers, autoresetting in the same step; that
    stack, built here around the registered env, steps through two episode ends and reports their returns."""
    def make():
        env = gym.make(ENV_ID, track_seed=PAPER_TRACK_SEEDS[0])
        env = gym.wrappers.FlattenObservation(env)
        env = gym.wrappers.RecordEpisodeStatistics(env)
        env = gym.wrappers.ClipAction(env)
        env = gym.wrappers.NormalizeObservation(env)
        env = gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -10, 10), env.observation_space)
        env = gym.wrappers.NormalizeReward(env, gamma=0.99)
        return gym.wrappers.TransformReward(env, lambda reward: np.clip(reward, -10, 10))

    envs = gym.vector.SyncVectorEnv([make, make], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    assert isinstance(envs.single_action_space, gym.spaces.Box) and envs.single_observation_space.shape == (6,)
    obs, _ = envs.reset(seed=1)
    returns = []
    for _ in range(420):
        obs, reward, terminated, truncated, infos = envs.step(np.random.default_rng(0).uniform(-1.5, 1.5, (2, 2)))
        assert np.isfinite(obs).all() and np.isfinite(reward).all()
        if "final_info" in infos:
            over = np.nonzero(infos["final_info"]["_episode"])[0]
            returns += list(infos["final_info"]["episode"]["r"][over])
            assert (infos["final_info"]["episode"]["l"][over] == 200).all()
    assert len(returns) == 4  # two cars, two 200-step episodes each
    envs.close()
