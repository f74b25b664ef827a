"""The batched TorchRL environment: specs, lockstep with Gymnasium, resets, seeding, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torchrl.envs import check_env_specs

from racing import RacingEnv, RacingTorchEnv, track_from_seed

TRACKS = [2067791, None, 5412436, 773203, None]


@pytest.mark.parametrize("num_envs, track_seeds", [(1, 2067791), (4, None), (5, TRACKS)])
def test_passes_torchrls_spec_check(num_envs, track_seeds):
    env = RacingTorchEnv(num_envs, track_seeds)
    env.set_seed(0)
    check_env_specs(env)


@pytest.mark.parametrize("track_seeds", [[5468063], TRACKS])
def test_lockstep_with_the_gymnasium_env(track_seeds):
    """Same tracks, seeds and actions: identical observations, rewards and flags, through
    crashes, time-limit resets and fresh random tracks."""
    n, seed, steps = len(track_seeds), 11, 450
    torch_env = RacingTorchEnv(n, track_seeds, max_steps=150)
    torch_env.set_seed(seed)
    gym_envs = [RacingEnv(track_seed=s, max_steps=150) for s in track_seeds]
    gym_obs = [env.reset(seed=seed + i)[0] for i, env in enumerate(gym_envs)]
    td = torch_env.reset()
    np.testing.assert_array_equal(td["observation"].numpy(), np.stack(gym_obs))
    rng = np.random.default_rng(0)
    for _ in range(steps):
        actions = rng.uniform(-1.1, 1.1, (n, 2)).astype(np.float32)
        td["action"] = torch.from_numpy(actions)
        stepped, td = torch_env.step_and_maybe_reset(td)
        nxt = stepped["next"]
        for i, env in enumerate(gym_envs):
            obs, reward, terminated, truncated, info = env.step(actions[i])
            np.testing.assert_array_equal(nxt["observation"][i].numpy(), obs)
            assert nxt["reward"][i].item() == np.float32(reward)
            assert nxt["terminated"][i].item() == terminated
            assert nxt["truncated"][i].item() == truncated
            assert nxt["done"][i].item() == (terminated or truncated)
            assert nxt["crashed"][i].item() == info["crashed"]
            assert nxt["checkpoint"][i].item() == info["checkpoint"]
            gym_obs[i] = env.reset()[0] if terminated or truncated else obs
        np.testing.assert_array_equal(td["observation"].numpy(), np.stack(gym_obs))


def test_fixed_tracks_are_there_before_reset():
    env = RacingTorchEnv(3, track_seeds=[2067791, None, 773203])
    assert env.tracks[0].seed == 2067791 and env.tracks[1] is None and env.tracks[2].seed == 773203
    np.testing.assert_array_equal(env.tracks[2].left_wall, track_from_seed(773203).left_wall)
    env.reset()
    assert env.tracks[1] is not None and env.tracks[0].seed == 2067791


@pytest.mark.parametrize("track_seeds", [[2067791, 773203], None])
def test_a_restored_simulator_continues_exactly(track_seeds):
    """Saved mid-episode (one car's episode just ended), restored into a new env: the next
    full reset continues the cars (resetting only the finished one) and every step after it
    is identical, random tracks included."""
    actions = torch.rand(150, 2, 2, generator=torch.Generator().manual_seed(1)) * 2 - 1
    env = RacingTorchEnv(2, track_seeds=track_seeds, max_steps=60)
    env.set_seed(4)
    env.reset_tensors()
    for k in range(90):
        out = env.step_tensors(actions[k])
        if out["done"].any():
            env.reset_tensors(out["done"])
    env.step_tensors(actions[90])  # t = 31: neither car is done
    saved = env.sim.state_dict()
    follow = [env.reset_tensors()] + [env.step_tensors(a) for a in actions[91:]]  # a plain full reset
    restored = RacingTorchEnv(2, track_seeds=track_seeds, max_steps=60)
    restored.set_seed(99)
    restored.load_sim_state(saved)
    first = restored.reset_tensors()
    assert restored.sim.t.tolist() == [31, 31]  # continued, not reset
    again = [first]
    for a in actions[91:]:
        again.append(restored.step_tensors(a))
    plain = RacingTorchEnv(2, track_seeds=track_seeds, max_steps=60)
    plain.load_sim_state(saved)
    expected = [plain.reset_tensors(torch.zeros(2, dtype=torch.bool))] + [plain.step_tensors(a) for a in actions[91:]]
    for got, want in zip(again, expected, strict=True):
        for key in want:
            assert torch.equal(got[key], want[key]), key
    assert not torch.equal(follow[1]["observation"], again[1]["observation"])  # a real reset differs


def test_partial_reset_leaves_other_cars_alone():
    env = RacingTorchEnv(3, 2067791)
    env.set_seed(0)
    td = env.reset()
    td["action"] = torch.tensor([[1.0, 0.1]] * 3)
    for _ in range(5):
        td = env.step(td)["next"].set("action", td["action"])
    before = env.sim.x.copy(), env.sim.t.copy()
    reset = torch.tensor([[False], [True], [False]])
    env.reset(td.clone().set("_reset", reset))
    assert env.sim.t.tolist() == [5, 0, 5]
    assert env.sim.x[0] == before[0][0] and env.sim.x[2] == before[0][2]
    assert env.sim.x[1] != before[0][1]


def test_time_limit_is_truncation_and_done():
    env = RacingTorchEnv(2, 1, max_steps=3)
    env.set_seed(0)
    td = env.rollout(3, break_when_any_done=False)
    assert td["next", "truncated"][:, -1].all() and td["next", "done"][:, -1].all()
    assert not td["next", "terminated"].any()
    assert not td["next", "done"][:, :-1].any()


def test_same_seed_same_rollout():
    def rollout(seed):
        env = RacingTorchEnv(4, None)
        env.set_seed(seed)
        torch.manual_seed(0)
        return env.rollout(250, break_when_any_done=False)

    a, b, c = rollout(3), rollout(3), rollout(4)
    assert (a == b).all()
    assert not torch.equal(a["next", "observation"], c["next", "observation"])


def test_collector_yields_one_episode_per_car_per_batch():
    from torchrl.collectors import Collector

    env = RacingTorchEnv(4, 2067791)
    env.set_seed(0)
    collector = Collector(env, policy=None, frames_per_batch=200 * 4, total_frames=2 * 200 * 4,
                          auto_register_policy_transforms=False)
    for batch in collector:
        assert batch.batch_size == torch.Size([4, 200])
        assert batch["next", "done"].sum().item() == 4
        assert batch["next", "done"][:, -1].all()
    collector.shutdown()


@pytest.mark.parametrize("action, error, message", [
    (torch.tensor([[float("nan"), 0.0], [0.0, 0.0]]), ValueError, r"cars \[0\] contain NaN or inf"),
    (torch.tensor([[0.0, 0.0], [float("inf"), 0.0]]), ValueError, r"cars \[1\] contain NaN or inf"),
    (torch.tensor([[0.0 + 1j, 0.0], [0.0, 0.0]]), TypeError, "is not a real number type"),
    (torch.tensor([[True, False], [True, False]]), TypeError, "is not a real number type"),
])
def test_bad_actions_get_clear_errors(action, error, message):
    env = RacingTorchEnv(2, 1)
    td = env.reset()
    td["action"] = action
    with pytest.raises(error, match=message):
        env.step(td)


def test_wrong_action_shape_is_refused():
    env = RacingTorchEnv(2, 1)
    td = env.reset()
    td.set("action", torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"action has shape \(2, 3\), expected \(2, 2\)"):
        env.step(td)


def test_set_seed_gives_car_i_the_stream_of_seed_plus_i():
    env = RacingTorchEnv(3, 2067791)
    env.set_seed(100)
    obs = env.reset()["observation"].numpy()
    for i in range(3):
        expected, _ = RacingEnv(track_seed=2067791).reset(seed=100 + i)
        np.testing.assert_array_equal(obs[i], expected)


def test_unknown_keyword_names_the_valid_ones():
    with pytest.raises(TypeError, match=r"unknown keyword\(s\) \['num_cars'\]; valid RacingConfig fields"):
        RacingTorchEnv(num_cars=3)


@pytest.mark.parametrize("options", [{}, {"history": 3, "privileged": True}, {"past_steps": 2}, {"track_seeds": None}])
def test_step_and_maybe_reset_is_torchrls_own(options):
    """The env's own step_and_maybe_reset (the Collector's step, without TorchRL's per-step checks)
    returns what EnvBase's does, entry for entry, through crashes and time-limit resets; a subclass
    that changes _step takes TorchRL's path."""
    from tensordict import TensorDict
    from torchrl.envs import EnvBase

    settings = {"num_envs": 4, "track_seeds": [2067791, 5412436, 773203, 5468063], "max_steps": 40, **options}
    ours, theirs = RacingTorchEnv(**settings), RacingTorchEnv(**settings)
    ours.set_seed(5), theirs.set_seed(5)
    carried_ours, carried_theirs = ours.reset(), theirs.reset()
    generator, crashes, resets = torch.Generator().manual_seed(0), 0, 0
    for t in range(160):
        action = torch.rand(4, 2, generator=generator) * 2 - 1
        action[0] = torch.tensor([1.0, 1.0])  # full throttle, full lock: off the road again and again
        for carried in (carried_ours, carried_theirs):
            carried["action"] = action.clone()
            carried["collector"] = TensorDict({"traj_ids": torch.arange(4)}, [4])  # a key the env does not know
        step_ours, carried_ours = ours.step_and_maybe_reset(carried_ours)
        step_theirs, carried_theirs = EnvBase._step_and_maybe_reset(theirs, carried_theirs)
        for got, expected in ((step_ours, step_theirs), (carried_ours, carried_theirs)):
            assert set(got.keys(True)) == set(expected.keys(True)), t
            assert all(torch.equal(got[key], expected[key]) for key in expected.keys(True, True)), t
        crashes += int(step_ours["next", "crashed"].sum())
        resets += int(step_ours["next", "done"].sum())
    assert crashes > 0 and resets >= 12

    class Counting(RacingTorchEnv):
        steps = 0

        def _step(self, tensordict):
            Counting.steps += 1
            return super()._step(tensordict)

    env = Counting(**settings)
    carried = env.reset()
    carried["action"] = torch.zeros(4, 2)
    env.step_and_maybe_reset(carried)
    assert Counting.steps == 1


def test_torchrl_s_own_gym_wrappers_run_the_registered_env():
    """TorchRL's standard wrappers of a registered Gymnasium env work on it: ``GymEnv('racing/Racing-v0')``
    (which passes ``frameskip`` and drops it when the env refuses it in Python's own words) and
    ``GymWrapper(gym.make(...))``; both pass ``check_env_specs`` and feed TorchRL's Collector."""
    import gymnasium as gym
    from torchrl.collectors import Collector
    from torchrl.envs import GymEnv, GymWrapper

    import racing  # noqa: F401 (registers racing/Racing-v0)

    for env in (GymEnv("racing/Racing-v0"), GymWrapper(gym.make("racing/Racing-v0"))):
        env.set_seed(0)
        check_env_specs(env)
        collector = Collector(env, None, frames_per_batch=50, total_frames=100, auto_register_policy_transforms=False)
        batches = list(collector)
        collector.shutdown()
        assert [b.batch_size for b in batches] == [torch.Size([50])] * 2
        assert batches[0]["next", "observation"].shape == (50, 6)
