"""The reactive ceiling by DAgger (pupil/dagger.py, imitate.py) at a tiny size."""

from __future__ import annotations

import pytest

from pupil.dagger import DATA_SEED, DaggerSettings


@pytest.mark.slow
def test_imitate_py_teaches_a_network_from_the_oracle_and_scores_it(tmp_path, capsys):
    import imitate

    table = tmp_path / "ceiling.csv"
    assert imitate.main(["--tracks", "2067791", "--rounds", "1", "--episodes", "1", "--epochs", "20",
                         "--labels", "mean", "--noise-states", "3", "--noise-labels", "2", "--table", str(table)]) == 0
    out = capsys.readouterr().out
    assert "track 2067791: round 0 " in out and ", round 1 " in out and "; oracle 172.2; final 0." in out
    assert "(400 labels, fit error 0." in out  # two rounds of one 200-step episode, every state labelled
    rows = table.read_text().splitlines()
    assert rows[0] == ("track,hidden,label,features,round,score,labels,fit_error,oracle,fraction,label_noise,"
                       "error_to_mean_label") and len(rows) == 3
    assert rows[1].startswith("2067791,100,mean,observation,0,") and rows[1].endswith(",,")  # repeated labels: last round only
    noise, error = map(float, rows[2].split(",")[-2:])
    assert noise >= 0 and error >= 0
    assert "; repeated labels: their variance " in out


@pytest.mark.slow
def test_a_privileged_pupil_sees_the_observation_and_the_car_s_true_state():
    from pupil.dagger import dagger, pupil_input
    from racing.gym_env import RacingEnv

    env = RacingEnv(track_seed=2067791)
    obs, _ = env.reset(seed=0)
    seen = pupil_input(env, obs, "state")
    assert seen.shape == (12,) and (seen[:6] == obs).all() and (0 <= seen[6:8]).all() and (seen[6:8] <= 1).all()
    assert pupil_input(env, obs, "observation") is obs
    result = dagger(2067791, DaggerSettings(rounds=0, episodes=1, epochs=2, features="state"))
    assert len(result.scores) == 1 and result.samples == [200]


def test_data_episodes_never_start_where_scored_ones_do_and_settings_are_checked():
    assert DATA_SEED >= 5  # scored episodes start from seeds 0-4
    with pytest.raises(ValueError, match="episodes must be at least 1"):
        DaggerSettings(episodes=0)
    with pytest.raises(ValueError, match="hidden a non-empty list"):
        DaggerSettings(hidden=())
    with pytest.raises(ValueError, match="label must be one of"):
        DaggerSettings(label="median")
    with pytest.raises(ValueError, match="features must be one of"):
        DaggerSettings(features="pixels")
    with pytest.raises(ValueError, match="noise_labels >= 2"):
        DaggerSettings(noise_states=10, noise_labels=1)


def test_the_oracle_offers_its_last_elite_mean_beside_its_action():
    from racing.oracle import Oracle, OracleSettings
    from racing.sim import RacingSim

    settings = OracleSettings(candidates=16, horizon=5, iterations=2)
    sim = RacingSim(1, 2067791)
    sim.seed(0)
    sim.reset()
    oracle = Oracle(settings=settings, seed=3)
    action = oracle.act(sim, 0)
    assert oracle.elite_mean.shape == action.shape == (2,) and abs(oracle.elite_mean).max() <= 1


@pytest.mark.slow
def test_the_documented_command_runs(tmp_path):
    """Each documented ``python imitate.py`` line, on one track at the smallest size (its other options as
    written: the network's width, the labels)."""
    import imitate
    from tests.test_readme import readme_commands

    lines = readme_commands("imitate.py")
    assert lines
    for args in lines:
        small = ["--tracks", "2067791", "--rounds", "0", "--episodes", "1", "--epochs", "2", "--processes", "1",
                 "--table", str(tmp_path / "ceiling.csv")]
        assert imitate.main([*args, *small]) == 0
