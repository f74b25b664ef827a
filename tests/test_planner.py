"""``python -m analysis.planner``: where a planning run's plans go wrong (docs/results/tdmpc2/README.md). Its
predictions are the model's own rollout and the plan's own scoring (``learners.latent.trajectory_values``); its
counts are checked on hand-made predictions; a crash's avoidability on the true simulator; its as-trained row is
the run's evaluation, and a variant with the run's own settings drives the same episodes."""

import csv
import math

import numpy as np
import pytest
import torch

from analysis import planner
from engine.evaluation import Policy, evaluate, load_policy
from tests.test_offpolicy import A
from tests.test_readme import readme_commands
from tests.test_start import train
from tests.test_tdmpc2 import SHORT


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("planner") / "run"
    train(folder, "algo=tdmpc2", *SHORT, "episodes=3", f"seed={A}")
    return folder


def _actor(run):
    policy, settings = load_policy(run)
    return planner.planning_actor(policy, run), policy, settings


def _episode(steps: int, seed: int = 0) -> planner.Episode:
    g = np.random.default_rng(seed)
    return planner.Episode(observations=list(g.random((steps, 6), dtype=np.float32)),
                           actions=list(g.uniform(-1, 1, (steps, 2)).astype(np.float32)),
                           rewards=list(g.random(steps)), crashed=[False] * steps)


@pytest.mark.slow
def test_predictions_are_the_model_s_rollout_and_the_plan_s_own_scoring(run):
    from learners.latent import trajectory_values

    actor, _, _ = _actor(run)
    model, h, gamma = actor.model, actor.options.horizon, 0.9
    episode = _episode(7)
    _, predicted, value, returns = planner.predictions(actor, episode, gamma)
    actions = torch.as_tensor(np.stack(episode.actions))
    with torch.no_grad():
        for t in range(7):
            state = model.encode(torch.as_tensor(episode.observations[t])[None, None])
            for k in range(max(h, planner.LOOKAHEAD)):
                if t + k >= 7:
                    assert math.isnan(predicted[k, t])
                    continue
                logits, state = model.step(state, actions[t + k][None, None])
                assert predicted[k, t] == pytest.approx(actor.support.value(logits).item(), abs=1e-5)
            if t + h > 7:
                assert math.isnan(value[t])
                continue
            scored = trajectory_values(model, actor.q_value, model.encode(torch.as_tensor(episode.observations[t])[None, None]),
                                       actions[t:t + h][None, None], torch.zeros(1, 1, 2), actor.support, gamma)
            assert value[t] == pytest.approx(scored.item(), abs=1e-4)
            assert returns[t] == pytest.approx(sum(gamma ** j * r for j, r in enumerate(episode.rewards[t:])))


def test_an_episode_s_crashes_are_the_simulator_s(run):
    from engine.evaluation import make_env

    _, policy, settings = _actor(run)
    env = make_env(settings, A)
    episode = planner.drive(policy, env, 0)
    assert len(episode.rewards) == len(episode.cars) == len(episode.actions) == 40
    assert sum(episode.crashed) == int(env.unwrapped.sim.crashes[0])
    assert episode.crashed == [r < -5 for r in episode.rewards]  # a crash costs 10, any other step earns 0 to 1
    assert episode.cars[0]["t"] == 0 and episode.cars[-1]["t"] == 39


def test_the_counts_are_those_of_the_predictions(run, monkeypatch):
    """A crash at step 30 of 80, foreseen from steps 30 and 28 (not 29); one false alarm at step 5; the plan's
    values one above the returns, four in the ten steps before the crash."""
    actor, _, _ = _actor(run)
    steps, crash = 80, 30
    episode = _episode(steps)
    episode.rewards = [0.5] * steps
    episode.rewards[crash], episode.crashed[crash] = -9.5, True
    predicted = np.full((3, steps), 0.5)
    for k in range(3):
        predicted[k, steps - k:] = np.nan
    predicted[0, crash], predicted[1, crash - 1], predicted[2, crash - 2] = -8.0, -1.0, -6.0
    predicted[0, 5] = -7.0
    returns = np.arange(steps, dtype=float)
    value = returns + 1.0
    value[crash - planner.BEFORE_CRASH:crash] += 3.0
    z = planner.predictions(actor, episode, 0.9)[0]  # the latent states (the model's way out reads them)
    monkeypatch.setattr(planner, "predictions", lambda *a: (z, predicted, value, returns))
    out = planner.readout(actor, episode, 0.9, 10.0)
    assert out["crashes"] == 1 and out["foreseen"] == [1, 0, 1]
    assert out["alarms"] == 1 and out["quiet"] == 79 + 78 + 77
    assert out["errors"] == pytest.approx(7.5) and out["error_count"] == 79 + 78 + 77
    usable = steps - planner.CUT_SHORT
    assert (out["near"], out["near_gap"]) == (10, pytest.approx(40.0))
    assert (out["far"], out["far_gap"]) == (usable - 10, pytest.approx(usable - 10.0))
    row = planner.pooled("r", A, "as trained", [out, out])
    assert row["crashes_per_episode"] == 1.0 and row["foreseen_0"] == 1.0 and row["foreseen_1"] == 0.0
    assert row["value_error_before_crash"] == 4.0 and row["value_error_elsewhere"] == 1.0


def test_the_summary_pairs_each_variant_with_the_policy_as_trained_by_run():
    def row(run, variant, reward, crashes, foreseen, before, elsewhere):
        return {"run": run, "variant": variant, "episodes": "5", "mean_reward": str(reward),
                "crashes_per_episode": str(crashes / 5), "crashes": str(crashes),
                **{c: str(foreseen) for c in planner.POOLED}, "value_error_before_crash": str(before),
                "value_error_elsewhere": str(elsewhere)}

    rows = [row("a", "as trained", 100, 10, 0.5, 4.0, 1.0), row("b", "as trained", 150, 0, "nan", "nan", 0.5),
            row("c", "as trained", 120, 5, 0.2, 3.0, 0.0),
            row("a", "prior", 90, 20, 1.0, 1.0, 1.0), row("b", "prior", 140, 1, 0.0, 2.0, 0.0),
            row("c", "prior", 130, 0, "nan", "nan", 0.0)]
    found = {(r["variant"], r["group"]): r for r in planner.summary_rows(rows, 1.0)}
    crashing = found[("as trained", "crashing")]
    assert crashing["runs"] == 2 and crashing["crashes_per_episode"] == 1.5 and crashing["mean_reward"] == 110
    assert crashing["foreseen_0"] == round((0.5 * 10 + 0.2 * 5) / 15, 4) and crashing["gain"] == 0
    assert crashing["value_gap"] == crashing["value_gap_high"] == 3.0  # 3.0 on both runs
    prior = found[("prior", "crashing")]  # runs a and c: gains -10 and +10
    assert (prior["gain"], prior["gain_low"]) == (0.0, round(-12.706 * math.sqrt(200) / math.sqrt(2), 2))
    assert prior["foreseen_2"] == 1.0 and prior["crashes_per_episode"] == 2.0
    assert found[("prior", "other")]["runs"] == 1 and found[("prior", "all")]["gain"] == round(-10 / 3, 2)


def test_a_crash_is_avoidable_only_where_some_action_keeps_the_car_on_the_track():
    from racing.sim import RacingSim

    sim = RacingSim(1, A)
    sim.seed(0)
    sim.reset()
    at_rest = {"x": 0.0, "y": 0.0, "theta": 0.0, "speed": 0.0, "checkpoint": 0, "t": 0}
    assert planner.avoidable(sim, at_rest, 5)
    # 10 px from the right wall (x = 100), heading straight at it at top speed: every action leaves in one step
    at_the_wall = {**at_rest, "x": 90.0, "y": 50.0, "theta": math.pi / 2, "speed": 50.0}
    assert not planner.avoidable(sim, at_the_wall, 1)


@pytest.mark.slow
def test_the_as_trained_row_is_the_evaluation_and_its_own_settings_drive_it_again(run, tmp_path, capsys):
    actor, policy, settings = _actor(run)
    h = actor.options.horizon
    table = tmp_path / "p.csv"
    assert planner.main([str(run), "--episodes", "2", "--variant", f"horizon={h}", "--variant", "prior",
                         "--table", str(table), "--summary", str(tmp_path / "s.csv")]) == 0
    with open(tmp_path / "s.csv", newline="") as f:
        summary = list(csv.DictReader(f))
    assert [(r["variant"], r["group"]) for r in summary if r["group"] == "all"] == [
        ("as trained", "all"), (f"horizon={h}", "all"), ("prior", "all")] and list(summary[0]) == list(planner.SUMMARY_COLUMNS)
    with open(table, newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["variant"] for r in rows] == ["as trained", f"horizon={h}", "prior"]
    assert list(rows[0]) == list(planner.COLUMNS)
    assert float(rows[0]["mean_reward"]) == round(evaluate(policy, settings, [A], 2)[A], 4)
    assert {k: v for k, v in rows[1].items() if k != "variant"} == {k: v for k, v in rows[0].items() if k != "variant"}
    prior = Policy(actor.net, stacked=True)
    assert float(rows[2]["mean_reward"]) == round(evaluate(prior, settings, [A], 2)[A], 4)
    assert f"| {run} | {A} | prior | 2 |" in capsys.readouterr().out
    for args in readme_commands("-m analysis.planner") or [["outputs/planner"]]:
        args = [str(run) if a.startswith("outputs/") else str(tmp_path / a) if a.endswith(".csv") else a for a in args]
        assert planner.main([*args, "--episodes", "1", "--processes", "1"]) == 0


@pytest.mark.parametrize("variant, message", [
    ("horizon", "expected 'prior' or KEY=VALUE"), ("speed=3", "KEY one of horizon"),
    ("horizon=0", "horizon must be in [1, 50]"), ("horizon=2.5", "horizon must be an integer"),
    ("temperature=nan", "temperature must be in"), ("horizon=2,horizon=3", "horizon given twice"),
])
def test_a_bad_variant_is_refused_in_one_line(variant, message, capsys):
    with pytest.raises(SystemExit):
        planner.main(["somewhere", "--variant", variant])
    assert message in capsys.readouterr().err


def test_the_start_states_stay_seeds(capsys):
    with pytest.raises(SystemExit):
        planner.main(["somewhere", "--episodes", "2", "--seed", str(2**32 - 1)])
    assert "--seed must be in [0, 2**32 - --episodes]" in capsys.readouterr().err


def test_variants_that_do_not_fit_the_run_and_runs_that_do_not_plan_are_refused(run, tmp_path, capsys):
    with pytest.raises(SystemExit):
        planner.main([str(run), "--table", str(tmp_path / "x.csv"), "--summary", str(tmp_path / "x.csv")])
    assert "name one file" in capsys.readouterr().err
    assert planner.main([str(run), "--variant", "samples=8,policy_samples=8"]) == 2
    assert "policy_samples (8) must be below samples (8)" in capsys.readouterr().err
    link = tmp_path / "link"
    link.symlink_to(run)
    assert planner.main([str(run), str(link), "--episodes", "1"]) == 0  # one run, named as first given
    printed = capsys.readouterr().out
    assert printed.count(f"| {A} | as trained |") == 1 and f"| {run} | {A} | as trained |" in printed
    no_penalty = tmp_path / "no_penalty"
    train(no_penalty, "algo=tdmpc2", *SHORT, "episodes=2", "env.options.crash_penalty=0", f"seed={A}")
    assert planner.main([str(no_penalty)]) == 2
    assert "crash_penalty=0" in capsys.readouterr().err
    prior_only = tmp_path / "prior_only"
    train(prior_only, "algo=tdmpc2", *SHORT, "episodes=2", "algo.tdmpc2.planning=false", f"seed={A}")
    assert planner.main([str(prior_only)]) == 2
    assert "not a planning run" in capsys.readouterr().err
    assert planner.main([str(run), str(prior_only), "--episodes", "1"]) == 2  # the other run read, this one named
    out, err = capsys.readouterr()
    assert f"| {run} | {A} | as trained |" in out and f"planner: skipped {prior_only}: not a planning run" in err
    assert planner.main([str(prior_only), str(run), "--variant", "elites=65"]) == 2  # checked before any driving
    out, err = capsys.readouterr()
    assert f"--variant 'elites=65' does not fit {run}: elites (65) must be at most samples (64)" in err and not out
