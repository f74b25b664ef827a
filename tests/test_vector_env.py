"""The native vector env (``gym.make_vec``) against Gymnasium's ``SyncVectorEnv`` of single envs."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import racing
from racing import PAPER_TRACK_SEEDS, RacingEnv, RacingVectorEnv
from racing.driver import ray_follower

# fixed and random tracks side by side (None first: SyncVectorEnv cannot batch an info key that is an
# int in its first env and None in a later one, such as the single env's track_seed)
TRACKS = [None, PAPER_TRACK_SEEDS[0], None, PAPER_TRACK_SEEDS[3]]


def sync_env(mode, tracks=TRACKS, **config):
    return SyncVectorEnv([lambda s=s: RacingEnv(track_seed=s, **config) for s in tracks], autoreset_mode=mode)


def actions(steps: int, n: int, seed: int = 0) -> np.ndarray:
    # mostly full throttle, so that cars crash, respawn and (on short tracks) finish
    rng = np.random.default_rng(seed)
    a = rng.uniform(-1, 1, size=(steps, n, 2))
    a[..., 0] = np.clip(a[..., 0] + 0.8, -1, 1)
    return a


def test_make_vec_gives_the_native_vector_env():
    env = gym.make_vec(racing.ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", track_seed=2067791)
    assert isinstance(env, RacingVectorEnv) and env.num_envs == 3
    assert env.single_observation_space == RacingEnv().observation_space
    assert env.observation_space.shape == (3, 6) and env.action_space.shape == (3, 2)
    assert env.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and info["step"].tolist() == [0, 0, 0] and info["_step"].all()
    assert isinstance(gym.make_vec(racing.ENV_ID, num_envs=2, vectorization_mode="sync"), SyncVectorEnv)
    assert isinstance(gym.make_vec(racing.ENV_ID, num_envs=2), RacingVectorEnv)  # the entry point is the default


# SAME_STEP: random tracks only (SyncVectorEnv's final_info hits the same int-then-None limit)
@pytest.mark.parametrize("mode, tracks", [(AutoresetMode.NEXT_STEP, TRACKS), (AutoresetMode.SAME_STEP, [None] * 4)])
def test_it_equals_a_sync_vector_env_of_single_envs(mode, tracks):
    """Across episode ends (truncation at 50 steps, finishes on 6-checkpoint tracks), crashes and
    random tracks: the same observations, rewards, flags and car states, bit for bit."""
    config = {"max_steps": 50, "num_segments": 6}
    ours = RacingVectorEnv(len(tracks), track_seed=tracks, autoreset_mode=mode, **config)
    theirs = sync_env(mode, tracks, **config)
    obs, info = ours.reset(seed=7)
    ref_obs, ref_info = theirs.reset(seed=7)
    np.testing.assert_array_equal(obs, ref_obs)
    ends = {"terminated": 0, "truncated": 0, "crashed": 0}
    noise = actions(200, len(tracks))
    for t in range(200):  # the ray follower with noise on cars 2 and 3: they finish, crash and time out
        a = ray_follower(obs).astype(np.float64)
        a[2:] = np.clip(a[2:] + 0.6 * noise[t, 2:], -1, 1)
        obs, reward, terminated, truncated, info = ours.step(a)
        ref = theirs.step(a)
        np.testing.assert_array_equal(obs, ref[0])
        np.testing.assert_array_equal(reward, ref[1])
        np.testing.assert_array_equal(terminated, ref[2])
        np.testing.assert_array_equal(truncated, ref[3])
        for key in ("x", "y", "theta", "speed", "checkpoint", "step", "progress", "crashed", "finished"):
            np.testing.assert_array_equal(info[key], ref[4][key], err_msg=key)
        if mode == AutoresetMode.SAME_STEP and (terminated | truncated).any():
            done = terminated | truncated
            np.testing.assert_array_equal(info["_final_obs"], ref[4]["_final_obs"])
            for car in np.flatnonzero(done):
                np.testing.assert_array_equal(info["final_obs"][car], ref[4]["final_obs"][car])
                assert info["final_info"]["step"][car] == ref[4]["final_info"]["step"][car] == 50 or terminated[car]
        ends["terminated"] += int(terminated.sum())
        ends["truncated"] += int(truncated.sum())
        ends["crashed"] += int(info["crashed"].sum())
    assert min(ends.values()) > 0, ends  # every kind of event happened


def test_disabled_autoreset_resets_the_masked_cars():
    ours = RacingVectorEnv(2, track_seed=[1, 2], autoreset_mode="Disabled", max_steps=5)
    theirs = sync_env(AutoresetMode.DISABLED, tracks=[1, 2], max_steps=5)
    np.testing.assert_array_equal(ours.reset(seed=3)[0], theirs.reset(seed=3)[0])
    for a in actions(5, 2):
        np.testing.assert_array_equal(ours.step(a)[0], theirs.step(a)[0])
    mask = np.array([True, False])
    obs, info = ours.reset(options={"reset_mask": mask})
    ref_obs, _ = theirs.reset(options={"reset_mask": mask})
    np.testing.assert_array_equal(obs, ref_obs)
    assert info["step"].tolist() == [0, 5]


def test_bad_input_is_refused_with_a_message():
    env = RacingVectorEnv(2, track_seed=1)
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros((2, 2)))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2,\), expected \(2, 2\)"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="NaN or inf"):
        env.step(np.array([[0.0, np.nan], [0.0, 0.0]]))
    with pytest.raises(ValueError, match="autoreset_mode must be one of"):
        RacingVectorEnv(2, autoreset_mode="sometimes")
    with pytest.raises(ValueError, match="does not render"):
        RacingVectorEnv(2, render_mode="human")
    with pytest.raises(ValueError, match="num_envs must be a positive integer"):
        RacingVectorEnv(0)
    with pytest.raises(ValueError, match="got 3 seeds for 2 cars"):
        env.reset(seed=[1, 2, 3])
    with pytest.raises(ValueError, match="reset_mask must be a bool array"):
        env.reset(options={"reset_mask": [1, 0]})
    with pytest.raises(TypeError):
        RacingVectorEnv(2, not_a_setting=1)
