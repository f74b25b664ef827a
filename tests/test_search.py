"""The reactive ceiling's direct policy search (``pupil.search``): its batched episodes are the env's episodes,
its actor is the run's deterministic policy, its choice is the best on the choice set, its scores are the
evaluation protocol's, and ``python -m pupil.search`` (as docs/beyond.md shows it) runs small and refuses
what it cannot search in one line."""

import csv
import math

import numpy as np
import torch

from engine.checkpoint import load_tensors
from engine.evaluation import drive_episode, evaluate, load_policy, make_env
from pupil import search as es
from racing.config import RacingConfig
from tests.test_offpolicy import A
from tests.test_readme import readme_commands
from tests.test_start import TINY, train


def start(tmp_path, *extra):
    folder = tmp_path / "start"
    train(folder, "algo=sac", *TINY, "episodes=2", f"seed={A}", *extra)
    return folder


def test_the_batched_episodes_are_the_env_s_and_the_actor_is_the_run_s_policy(tmp_path):
    folder = start(tmp_path)
    state = es.deterministic_state(load_tensors(folder / "actor.pt", "actor"), gaussian=True)
    actor = es.Actor(state)
    policy, settings = load_policy(folder)
    observations = torch.rand(1, 32, 6, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 2
    np.testing.assert_allclose(actor.act(actor.theta[None], observations)[0].numpy(),
                               policy.actions(observations[0].float()).numpy(), atol=1e-5)
    config = RacingConfig(max_steps=40)
    flat = torch.stack([actor.theta, actor.theta + 0.05])
    batched = es.returns(actor, flat, A, [3, 7], config)
    env = make_env(settings, A)
    for c in range(2):
        def act(_env, obs, c=c):
            x = torch.as_tensor(np.asarray(obs, np.float32), dtype=torch.float64).reshape(1, 1, -1)
            return actor.act(flat[c:c + 1], x).reshape(2).numpy()
        assert [drive_episode(act, env, s) for s in (3, 7)] == batched[c].tolist()


def test_the_chosen_weights_are_the_best_on_the_choice_set_and_score_as_the_protocol_does(tmp_path):
    folder = start(tmp_path)
    settings = es.SearchSettings(generations=4, pairs=3, episodes=2, choose_every=2, choice=2, protocol=2, score=3)
    result = es._search_run(folder, settings)
    assert [g for g, _ in result.choice] == [0, 2, 4]
    best = max(result.choice, key=lambda item: item[1])
    assert result.chosen_generation == best[0]
    policy, recorded = load_policy(folder)
    assert result.start["protocol"] == evaluate(policy, recorded, [A], 2)[A]  # the start is the run's own policy
    from engine.evaluation import make_policy

    start_state = load_tensors(folder / "actor.pt", "actor")
    assert all(torch.equal(result.weights[k][2:], start_state[k][2:]) for k in ("0.layers.1.weight", "0.layers.1.bias"))
    found = make_policy("sac", recorded["network"], RacingConfig(max_steps=40).obs_size, result.weights)
    assert evaluate(found, recorded, [A], 2)[A] == result.found["protocol"]
    assert math.isclose(result.found["fresh"], sum(result.found["fresh_episodes"]) / 3)


def test_the_documented_search_runs_small_and_refuses_what_it_cannot_search(tmp_path, capsys):
    folder = start(tmp_path)
    lines = readme_commands("-m pupil.search")
    assert lines, "docs/beyond.md shows the search"
    small = ["--generations", "2", "--pairs", "2", "--episodes", "1", "--choose-every", "1", "--choice", "1",
             "--protocol", "1", "--score", "2"]
    for i, args in enumerate(lines):  # each documented line, small, on this test's run
        args = [str(folder) if a.startswith("outputs/") else a for a in args]
        args = [str(tmp_path / f"doc{i}-{a}") if a.endswith(".csv") or a == "found" else a for a in args]
        assert es.main([*args, *small]) == 0, args
    capsys.readouterr()
    table, out = tmp_path / "search.csv", tmp_path / "found"
    assert es.main([str(folder), *small, "--table", str(table), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| track | oracle |" in printed and f"| {A} |" in printed
    rows = list(csv.DictReader(table.read_text().splitlines()))
    assert rows[0]["track"] == str(A) and math.isfinite(float(rows[0]["found_fresh"]))
    assert set(load_tensors(out / f"policy-{A}.pt", "policy")) == {"0.layers.0.weight", "0.layers.0.bias",
                                                                   "0.layers.1.weight", "0.layers.1.bias"}
    try:
        es.main([str(folder), "--pairs", "32000", "--episodes", "8"])  # a thousand times the default pairs
    except SystemExit as stop:
        assert stop.code == 2
    assert "cars at once, above 100,000" in capsys.readouterr().err
    assert es.main([str(tmp_path / "nowhere")]) == 2
    assert "search:" in capsys.readouterr().err
    relu = tmp_path / "relu"
    train(relu, "algo=sac", *TINY, "episodes=2", f"seed={A}", "network.activation=relu")
    assert es.main([str(folder), str(relu), "--generations", "1"]) == 2  # one run a track: one row, one file
    assert "search one run a track" in capsys.readouterr().err
    assert es.main([str(relu), "--generations", "1"]) == 2
    assert "tanh hidden units" in capsys.readouterr().err
    random_track = tmp_path / "random"
    train(random_track, "algo=sac", *TINY, "episodes=2", f"seed={A}", "env.track=random")
    assert es.main([str(random_track), "--generations", "1"]) == 2
    assert "one fixed track" in capsys.readouterr().err
