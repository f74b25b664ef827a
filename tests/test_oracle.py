"""The oracle (a planning controller on the true simulator state): exact rollouts, reproducible
scores, and the command that scores it."""

from __future__ import annotations

import csv

import numpy as np
import pytest

import racing
from racing.driver import ray_follower
from racing.oracle import Oracle, OracleSettings, drive, score

SMALL = OracleSettings(candidates=32, horizon=15, iterations=2)
TRACK = racing.PAPER_TRACK_SEEDS[0]


def test_a_planned_rollout_is_what_the_car_then_does():
    """The planner copies the car's true state: a candidate's planned return equals the reward the
    car collects when it drives that sequence (crashes and respawns included)."""
    env = racing.RacingEnv(track_seed=TRACK)
    env.reset(seed=3)
    for action in np.tile([1.0, 0.3], (25, 1)):  # mid-episode, at speed
        env.step(action)
    oracle = Oracle(SMALL, seed=0)
    sequences = np.random.default_rng(1).uniform(-1, 1, (SMALL.candidates, 40, 2))
    sequences[:, :, 0] = 1.0  # fast enough to crash
    planned = oracle._rollout(env.unwrapped.sim, 0, sequences)
    state = env.unwrapped.sim.state_dict()
    crashes = 0
    for k in (0, 7, 31):
        env.unwrapped.sim.load_state_dict(state)
        total = 0.0
        for action in sequences[k]:
            _, reward, terminated, truncated, info = env.step(action)
            total += reward
            crashes += info["crashed"]
        assert total == pytest.approx(planned[k], abs=1e-9)
    assert crashes > 0


def test_the_oracle_is_reproducible_and_beats_the_hand_written_driver():
    env = racing.RacingEnv(track_seed=TRACK)
    first = drive(env, Oracle(SMALL, seed=5), seed=0)
    assert drive(env, Oracle(SMALL, seed=5), seed=0) == first
    obs, _ = env.reset(seed=0)
    driver, done = 0.0, False
    while not done:
        obs, reward, terminated, truncated, _ = env.step(ray_follower(obs))
        driver += reward
        done = terminated or truncated
    assert first > driver + 5, (first, driver)


@pytest.mark.slow
def test_the_oracle_drives_as_it_did_when_its_scores_were_shipped():
    """The first of the five episodes whose mean is analysis/data/oracle_tuning.csv's track 1001
    (174.875741), to the bit as the code that made it drove it."""
    assert score([1001], 1, 0)[1001]["episodes"] == [174.5600009852249]


def test_bad_settings_are_refused():
    for bad in (dict(candidates=0), dict(horizon=1.5), dict(elite=0.0), dict(min_std=1.0, init_std=0.5)):
        with pytest.raises(ValueError, match="oracle"):
            OracleSettings(**bad)


def test_the_documented_oracle_command_runs(tmp_path):
    """``evaluate.py --oracle ...`` as the docs show it, at one episode and a small budget."""
    import evaluate
    from tests.test_readme import readme_commands

    commands = [c for c in readme_commands("evaluate.py", include_elsewhere=True) if "--oracle" in c]
    assert commands, "the docs show no evaluate.py --oracle command"
    for args in commands:
        args = list(args)
        args[args.index("--episodes") + 1] = "1"
        table = tmp_path / "oracle.csv"
        args = [str(table) if a.endswith(".csv") else a for a in args]
        assert evaluate.main([*args, "--candidates", "16", "--horizon", "10", "--iterations", "1"]) == 0
        if "--table" in args:
            with open(table) as f:
                rows = list(csv.DictReader(f))
            assert [int(r["track"]) for r in rows] == [int(t) for t in args[args.index("--tracks") + 1:
                                                                             args.index("--episodes")]]
    assert score([TRACK], 1, settings=SMALL)[TRACK]["mean"] > 0
