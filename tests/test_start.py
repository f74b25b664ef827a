"""A run started from another run's actor (``algo.td.start_from``, ``engine.start``), its critics fitted first
(``algo.td.critic_first_episodes``), and the deterministic policy scored during training (``eval_every``): the
pieces of docs/beyond.md's decisive experiment.

Checked: the started actor is the start's, bit for bit (a held actor ends as it began, its temperature too); a
Gaussian actor's mean starts a deterministic one that acts as the Gaussian's deterministic policy; a member of a
population starts from its own member folder, as its solo run does; the critics train while the actor is held,
and the actor trains after; ``eval_every`` changes no training number and scores what ``evaluate.py`` scores; a
start that cannot be this run's actor is refused in one line.
"""

import csv
import json

import numpy as np
import pytest
import torch

from engine.config import ConfigError, RunConfig
from engine.evaluation import evaluate, load_policy
from engine.runner import train_population
from tests.test_config import load
from tests.test_offpolicy import A, B
from tests.test_train import run_train

TINY = ["er=memory", "env.options.max_steps=40", "er.buffer_size=400", "algo.td.warmup_episodes=1",
        "algo.td.updates_per_step=0.25", "progress=false", "logger=none", "final_window=2"]


def train(folder, *overrides):
    """A run of ``overrides`` into ``folder``, its settings recorded as train.py records them."""
    settings = RunConfig.compose_mapping(*overrides)
    return train_population(RunConfig.from_mapping(settings), folder, settings)


def rows(folder):
    with open(folder / "metrics.csv") as f:
        return list(csv.DictReader(f))


def start_run(tmp_path, algo="sac", seeds=(A,)):
    """A finished run to start from (a population's folder when several seeds)."""
    folder = tmp_path / f"start_{algo}_{len(seeds)}"
    members = f"seed={seeds[0]}" if len(seeds) == 1 else f"seeds=[{','.join(map(str, seeds))}]"
    train(folder, f"algo={algo}", *TINY, "episodes=3", members)
    return folder


def states(folder, name="actor"):
    from engine.checkpoint import load_tensors

    return load_tensors(folder / f"{name}.pt", name)


@pytest.mark.slow
def test_a_run_started_with_critics_holds_its_start_s_networks_until_its_first_steps(tmp_path):
    start = start_run(tmp_path)
    run = tmp_path / "both"
    summary = train(run, "algo=sac", *TINY, "episodes=1", f"seed={A}", "algo.td.warmup_episodes=0",
                    f"algo.td.start_from={start}", f"algo.td.start_critics_from={start}")[0]
    for name in ("actor", "critic"):
        ours, theirs = states(run, name), states(start, name)
        assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours), name
    assert summary["start"]["critics"]["folder"] == str(start.resolve())
    narrow = tmp_path / "narrow"
    train(narrow, "algo=sac", *TINY, "episodes=2", f"seed={A}", "network.critic_hidden=[8,8]")
    refused = run_train("algo=sac", *TINY, "episodes=1", f"seed={A}", f"algo.td.start_from={start}",
                        f"algo.td.start_critics_from={narrow}", f"hydra.run.dir={tmp_path / 'other'}")
    assert refused.returncode != 0 and "algo.td.start_critics_from" in refused.stderr.splitlines()[-1]
    alone = run_train("algo=sac", *TINY, "episodes=1", f"seed={A}", f"algo.td.start_critics_from={start}",
                      f"hydra.run.dir={tmp_path / 'alone'}")
    assert alone.returncode != 0 and "give algo.td.start_from too" in alone.stderr


def test_a_search_s_weights_start_a_run_from_its_folder_or_file(tmp_path):
    from engine.checkpoint import save_tensors

    start = start_run(tmp_path)
    found = tmp_path / "found"
    found.mkdir()
    weights = {k: v + 0.01 for k, v in states(start).items()}
    save_tensors(found / f"policy-{A}.pt", weights)
    for source in (found, found / f"policy-{A}.pt"):
        run = tmp_path / f"from_{source.name}"
        summary = train(run, "algo=td3", *TINY, "episodes=1", f"seed={A}", f"algo.td.start_from={source}")[0]
        assert torch.equal(states(run)["0.layers.1.weight"], weights["0.layers.1.weight"][:2])
        assert summary["start"]["file"] == str((found / f"policy-{A}.pt").resolve())
    save_tensors(found / f"policy-{A}.pt", {**weights, "0.layers.0.bias": torch.full((100,), float("nan"))})
    refused = run_train("algo=td3", *TINY, "episodes=1", f"seed={A}", f"algo.td.start_from={found}",
                        f"hydra.run.dir={tmp_path / 'nan'}")
    assert refused.returncode != 0 and "non-finite" in refused.stderr.splitlines()[-1]


def test_a_held_actor_ends_as_the_start_began_and_its_critics_train(tmp_path):
    start = start_run(tmp_path)
    run = tmp_path / "held"
    summary = train(run, "algo=sac", *TINY, "episodes=3", f"seed={A}", "algo.td.warmup_episodes=0",
          f"algo.td.start_from={start}", "algo.td.critic_first_episodes=3")[0]
    ours, theirs = states(run), states(start)
    assert ours.keys() == theirs.keys() and all(torch.equal(ours[k], theirs[k]) for k in ours)
    metrics = rows(run)
    assert [r["actor/alpha"] for r in metrics[1:]] == ["1.0", "1.0"]  # the temperature held as well
    assert metrics[1]["critic/loss_qvalue"] != metrics[2]["critic/loss_qvalue"]
    assert summary["start"]["folder"] == str(start.resolve()) and summary["start"]["episodes"] == 3
    assert len(summary["start"]["actor_sha256"]) == 64
    # one episode fewer held: the actor's steps before the last episode move it
    moved = tmp_path / "moved"
    train(moved, "algo=sac", *TINY, "episodes=3", f"seed={A}", "algo.td.warmup_episodes=0",
          f"algo.td.start_from={start}", "algo.td.critic_first_episodes=1")
    assert not torch.equal(states(moved)["0.layers.0.weight"], theirs["0.layers.0.weight"])
    assert rows(moved)[2]["actor/alpha"] != "1.0"


def test_a_gaussian_actor_s_mean_starts_a_deterministic_actor_that_drives_as_it_did(tmp_path):
    start = start_run(tmp_path)
    run = tmp_path / "td3"
    train(run, "algo=td3", *TINY, "episodes=2", f"seed={A}", f"algo.td.start_from={start}",
          "algo.td.critic_first_episodes=2")
    sac, _ = load_policy(start)
    td3, settings = load_policy(run)
    observations = torch.rand(64, 6, generator=torch.Generator().manual_seed(0)) * 2
    assert torch.equal(sac.actions(observations), td3.actions(observations))
    assert evaluate(sac, settings, [A], 1) == evaluate(td3, settings, [A], 1)
    refused = run_train("algo=sac", *TINY, "episodes=2", f"seed={A}", f"algo.td.start_from={run}",
                        f"hydra.run.dir={tmp_path / 'back'}")
    assert refused.returncode != 0
    assert "algo.td.start_from: a deterministic actor has no scale" in refused.stderr, refused.stderr[-2000:]


def test_a_member_starts_from_its_own_member_folder_as_its_solo_run_does(tmp_path):
    start = start_run(tmp_path, seeds=(A, B))
    common = ["algo=sac", *TINY, "episodes=2", f"algo.td.start_from={start}", "algo.td.critic_first_episodes=1"]
    members = train(tmp_path / "pop", *common, f"seeds=[{A},{B}]")
    solo = train(tmp_path / "solo", *common, f"seed={B}")[0]
    assert [m["start"]["folder"] for m in members] == [str((start / f"seed{s}").resolve()) for s in (A, B)]
    assert solo["start"] == members[1]["start"]
    assert (tmp_path / "solo" / "metrics.csv").read_bytes() == (tmp_path / "pop" / f"seed{B}" / "metrics.csv").read_bytes()


def test_eval_every_scores_the_policy_as_evaluate_does_and_changes_no_training_number(tmp_path):
    plain = ["algo=sac", *TINY, "episodes=4", f"seed={A}", "eval_seeds=[1001]", "eval_episodes=2"]
    train(tmp_path / "plain", *plain)
    summary = train(tmp_path / "scored", *plain, "eval_every=2")[0]
    without, with_scores = rows(tmp_path / "plain"), rows(tmp_path / "scored")
    assert [{k: v for k, v in r.items() if k != "deterministic"} for r in with_scores] == without
    scores = [r["deterministic"] for r in with_scores]
    assert scores[0] == scores[2] == "" and scores[1] and scores[3]
    assert float(scores[3]) == summary["evaluation"]["own_track"]  # the final policy, as the end-of-run evaluation
    policy, settings = load_policy(tmp_path / "scored")
    assert evaluate(policy, settings, [A], 2)[A] == float(scores[3])


@pytest.mark.slow
def test_a_start_that_cannot_be_this_run_s_actor_is_refused_in_one_line(tmp_path):
    start = start_run(tmp_path)
    torch.save([1, 2, 3], tmp_path / "list.pt")
    with open(tmp_path / "huge.pt", "wb") as f:  # sparse: 4.8 GB was read whole (13.7 GB resident) on 35048d1
        f.truncate(4_800_000_000)
    cases = {
        f"algo.td.start_from={tmp_path / 'huge.pt'}": "more than an actor holds",
        f"algo.td.start_from={tmp_path / 'nowhere'}": "does not exist",
        f"algo.td.start_from={tmp_path / 'list.pt'}": "is not an actor's weights",
        "network.actor_hidden=[7]": "algo.td.start_from: ",
        "algo.td.observation_norm=true": "observation_norm",
    }
    for i, (override, said) in enumerate(cases.items()):
        extra = [] if "start_from" in override else [f"algo.td.start_from={start}"]
        result = run_train("algo=sac", *TINY, "episodes=2", f"seed={A}", override, *extra,
                           f"hydra.run.dir={tmp_path / f'refused{i}'}")
        assert result.returncode != 0, override
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert said in lines[-1] and "Traceback" not in result.stderr, (override, result.stderr[-2000:])
    for value in ("' '", "[1]"):
        try:
            load("algo=sac", f"algo.td.start_from={value}")
        except ConfigError as err:
            assert "start_from" in str(err)
        else:
            raise AssertionError(value)
    assert np.isfinite(json.loads((start / "summary.json").read_text())["final_mean"])


@pytest.mark.slow
def test_a_bad_start_refuses_before_overwrite_clears_and_a_changed_start_is_not_resumed(tmp_path):
    import shutil

    from engine.processes import STOP_FILE, RunStopped

    start = start_run(tmp_path)
    finished = tmp_path / "finished"
    train(finished, "algo=sac", *TINY, "episodes=2", f"seed={A}")
    kept = (finished / "summary.json").read_bytes()
    for source in (tmp_path / "nowhere", finished):  # missing; the run's own folder (overwrite would clear it)
        result = run_train("algo=sac", *TINY, "episodes=2", f"seed={A}", "overwrite=true",
                           f"algo.td.start_from={source}", f"hydra.run.dir={finished}")
        assert result.returncode != 0 and "algo.td.start_from" in result.stderr.splitlines()[-1], result.stderr[-2000:]
        assert (finished / "summary.json").read_bytes() == kept and (finished / "actor.pt").exists()
    # a run stopped after its first episode keeps what it started from; another start under the same path is refused
    stopped = tmp_path / "stopped"
    stopped.mkdir()
    (stopped / STOP_FILE).write_text("")
    overrides = ["algo=sac", *TINY, "episodes=3", f"seed={A}", f"algo.td.start_from={start}", "checkpoint_every=1"]
    settings = RunConfig.compose_mapping(*overrides)
    with pytest.raises(RunStopped, match="saved at episode 1"):
        train_population(RunConfig.from_mapping(settings), stopped, settings, stop_file=stopped / STOP_FILE)
    (stopped / STOP_FILE).unlink()
    shutil.rmtree(start)
    train(start, "algo=sac", *TINY, "episodes=3", f"seed={A}", "algo.td.updates_per_step=0.5")  # other weights
    with pytest.raises(ConfigError, match="began from other weights"):
        train(stopped, *overrides)


def test_a_held_actor_for_the_whole_run_and_an_empty_deterministic_column_are_noted(capsys):
    load("algo=sac", "episodes=4", "algo.td.critic_first_episodes=3", "eval_every=7")
    said = capsys.readouterr().err
    assert "algo.td.critic_first_episodes=3 with episodes=4: the actor is held through the whole run" in said
    assert "eval_every=7 is larger than episodes=4: metrics.csv's deterministic column stays empty" in said
    load("algo=sac", "episodes=5", "algo.td.critic_first_episodes=3", "eval_every=5")
    assert "held through" not in capsys.readouterr().err
