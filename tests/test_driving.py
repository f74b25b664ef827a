"""``python -m analysis.driving``: how a trained policy drives beside the oracle (docs/beyond.md, "Where the
gap to the oracle is"). Checked on a tiny run: the policy's row is its evaluation (the same episodes,
the same total reward), the oracle's row is the oracle's own score on those episodes, the throttle shares
are those of the actions taken, and the full-throttle diagnostic changes only the throttles it names."""

import csv

import pytest

from analysis import driving
from engine.config import RunConfig
from engine.evaluation import evaluate, load_policy
from engine.runner import train_population


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("driving") / "run"
    settings = RunConfig.compose_mapping("algo=sac", "er=memory", "episodes=2", "algo.td.warmup_episodes=1",
                                         "algo.td.updates_per_step=0.1", "env.options.max_steps=30", "seed=1001",
                                         "progress=false", "logger=none")
    train_population(RunConfig.from_mapping(settings), folder, settings)
    return folder


@pytest.mark.slow
def test_the_rows_are_the_policy_s_evaluation_and_the_oracle_s_score(run, tmp_path, capsys):
    from racing import oracle
    from racing.config import RacingConfig

    assert driving.main([str(run), "--episodes", "2", "--table", str(tmp_path / "d.csv")]) == 0
    with open(tmp_path / "d.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["driver"] for r in rows] == [str(run), "oracle"] and "| oracle | 1001 | 2 |" in capsys.readouterr().out
    policy, settings = load_policy(run)
    assert float(rows[0]["mean_reward"]) == round(evaluate(policy, settings, [1001], 2)[1001], 4)
    planned = oracle.score([1001], 2, config=RacingConfig(max_steps=30))[1001]["mean"]
    assert float(rows[1]["mean_reward"]) == round(planned, 4)
    for row in rows:
        assert 0 <= float(row["braking"]) + float(row["full_throttle"]) <= 1
        assert -1 <= float(row["mean_throttle"]) <= 1 and float(row["mean_speed"]) > 0


def test_the_full_throttle_diagnostic_changes_only_the_throttles_it_names(run):
    from engine.evaluation import make_env

    policy, settings = load_policy(run)
    env = make_env(settings, 1001)
    plain = driving.drive(lambda e, o: policy(o), env, 0, policy.reset)
    rows = driving.driving_rows([run], 1, oracle=False, full_throttle_above=-1.0)  # every throttle made full
    assert rows[0] == driving.summarise(str(run), 1001, [plain])
    assert rows[1]["driver"].endswith("(throttle >= -1 -> 1)") and rows[1]["full_throttle"] == 1.0
    assert rows[1]["mean_throttle"] == 1.0 and rows[1]["braking"] == 0.0


@pytest.mark.parametrize("args, message", [(["--episodes", "0"], "argument --episodes: must be in [1, 1,000], got 0"),
                                           (["--full-throttle-above", "2"], "argument --full-throttle-above: must be a finite number in [-1, 1], got 2")])
def test_bad_arguments_are_refused(run, args, message, capsys):
    with pytest.raises(SystemExit):
        driving.main([str(run), *args])
    assert message in capsys.readouterr().err


def test_a_table_goes_into_new_folders_a_folder_is_refused_first_and_a_run_named_twice_drives_once(run, tmp_path,
                                                                                                   capsys):
    with pytest.raises(SystemExit):
        driving.main([str(run), "--no-oracle", "--table", str(tmp_path)])
    assert "is a folder; give a file name" in capsys.readouterr().err
    table = tmp_path / "new" / "folder" / "d.csv"
    assert driving.main([str(run), str(run) + "/", "--no-oracle", "--episodes", "1", "--table", str(table)]) == 0
    with open(table, newline="") as f:
        assert len(list(csv.DictReader(f))) == 1


def test_a_folder_without_runs_is_refused_in_one_line(tmp_path, capsys):
    assert driving.main([str(tmp_path)]) == 2
    assert "holds no finished train.py run" in capsys.readouterr().err


@pytest.mark.slow
def test_the_documented_command_runs(run, tmp_path):
    """docs/beyond.md's ``python -m analysis.driving <run folder>`` line, on the tiny run (one episode)."""
    from tests.test_readme import readme_commands

    lines = readme_commands("-m analysis.driving")
    assert lines
    for args in lines:
        args = [str(run) if a.startswith("outputs/") else a for a in args]
        assert driving.main([*args, "--episodes", "1", "--table", str(tmp_path / "d.csv")]) == 0
