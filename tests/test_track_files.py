"""Tracks from files and closed circuits with laps (racing/track_file.py, tracks.py): loading,
every refusal with its line, export, the environments on file tracks and circuits (check_env,
check_env_specs, the vector env against single envs, exact resume mid-lap), and training on a file."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import racing
from racing.driver import ray_follower
from racing.sim import RacingSim
from racing.track import track_from_seed
from racing.track_file import TrackFileError, example, load_track, save_track, track_config
from racing.vector_env import RacingVectorEnv
from tests.test_readme import readme_commands, stand_in_circuits
from tests.test_train import ENV, ROOT
from tests import zygote

HEADER = "# x_m,y_m,w_tr_right_m,w_tr_left_m\n"


def write(tmp_path: Path, body: str, name: str = "track.csv") -> Path:
    path = tmp_path / name
    path.write_text(body)
    return path


def test_the_example_files_load_as_circuits_and_an_open_track():
    oval, kidney, paper = (load_track(example(name)) for name in ("oval", "kidney", "paper_2067791"))
    assert (oval.closed, kidney.closed, paper.closed) == (True, True, False)
    assert (oval.num_checkpoints, kidney.num_checkpoints, paper.num_checkpoints) == (56, 72, 50)
    for track in (oval, kidney, paper):  # placed as generated tracks are: start line at y = -10, heading +y
        start = (track.left_wall[0] + track.right_wall[0]) / 2
        np.testing.assert_allclose(start, [0.0, -10.0], atol=1e-9)
        assert track.left_wall[0][0] < 0 < track.right_wall[0][0]
    with pytest.raises(TrackFileError, match="no example track 'monza'"):
        example("monza")


def test_an_exported_track_reloads_with_the_same_walls_from_its_third_point(tmp_path):
    for seed in racing.PAPER_TRACK_SEEDS:
        generated = track_from_seed(seed)
        loaded = load_track(save_track(generated, tmp_path / f"{seed}.csv"))
        assert not loaded.closed and loaded.num_checkpoints == generated.num_checkpoints
        for wall, other in ((generated.left_wall, loaded.left_wall), (generated.right_wall, loaded.right_wall)):
            lengths = np.hypot(*np.diff(wall, axis=0).T)
            np.testing.assert_allclose(np.hypot(*np.diff(other, axis=0).T)[2:], lengths[2:], rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.hypot(*(loaded.left_wall - loaded.right_wall).T), 200.0, rtol=1e-12)


@pytest.mark.parametrize("body, message", [
    (HEADER + "0,0,10\n0,100,10,10\n0,200,10,10\n", "line 2: expected 4 values"),
    (HEADER + "0,0,10,10\n0,100,ten,10\n0,200,10,10\n", "line 3: w_tr_right_m is 'ten', not a number"),
    (HEADER + "0,0,10,10\n0,nan,10,10\n0,200,10,10\n", "line 3: y_m is nan, not a finite number"),
    (HEADER + "0,0,10,10\n0,100,0,10\n0,200,10,10\n", "line 3: w_tr_right_m must be > 0 (a width), got 0"),
    (HEADER + "0,0,10,10\n0,100,10,-3\n0,200,10,10\n", "line 3: w_tr_left_m must be > 0 (a width), got -3"),
    (HEADER + "0,0,10,10\n0,100,10,10\n", "2 point(s); a track needs at least 3"),
    (HEADER + "0,0,10,10\n0,100,10,10\n0,100,10,10\n0,300,10,10\n", "line 4: repeats the point of line 3"),
    (HEADER + "0,0,30,30\n0,100,30,30\n100,100,30,30\n100,0,30,30\n0,50,30,30\n",
     "the walls cross themselves: the left wall between the points of lines"),
    ("# closed: maybe\n" + HEADER + "0,0,10,10\n", "line 1: closed must be true or false, got 'maybe'"),
    ("# scale: -2\n" + HEADER + "0,0,10,10\n", "line 1: scale must be a number > 0, got '-2'"),
])
def test_a_bad_file_is_refused_with_its_line_and_problem(tmp_path, body, message):
    path = write(tmp_path, body)
    with pytest.raises(TrackFileError, match=re.escape(message)):
        load_track(path)
    with pytest.raises(TrackFileError):  # and no environment is half built on it
        gym.make("racing/Racing-v0", track_file=path)


def test_a_missing_file_and_wrong_arguments_are_refused(tmp_path):
    with pytest.raises(TrackFileError, match="cannot be read"):
        load_track(tmp_path / "missing.csv")
    with pytest.raises(ValueError, match="give track seeds or a track_file, not both"):
        gym.make("racing/Racing-v0", track_seed=1, track_file=example("oval"))
    with pytest.raises(ValueError, match="num_segments comes from the track file"):
        gym.make("racing/Racing-v0", track_file=example("oval"), num_segments=10)
    with pytest.raises(ValueError, match="track_scale and track_closed apply to a track_file"):
        gym.make("racing/Racing-v0", track_closed=True)


@pytest.mark.parametrize("name", ["oval", "paper_2067791"])
def test_check_env_and_check_env_specs_pass_on_file_tracks(name):
    from gymnasium.utils.env_checker import check_env
    from torchrl.envs.utils import check_env_specs

    from racing.torchrl_env import RacingTorchEnv

    check_env(gym.make("racing/Racing-v0", track_file=example(name)).unwrapped, skip_render_check=True)
    check_env_specs(RacingTorchEnv(3, track_file=example(name)), seed=0)


def test_a_circuit_counts_laps_and_their_times():
    env = gym.make("racing/Racing-v0", track_file=example("oval"), max_steps=800)
    obs, info = env.reset(seed=3)
    assert info["laps"] == 0 and info["lap_times"] == [] and info["crashes"] == 0
    laps_seen, terminated = [], False
    for _ in range(800):
        obs, reward, terminated, truncated, info = env.step(ray_follower(obs))
        assert not terminated  # a circuit has no finish
        laps_seen.append(info["laps"])
        if truncated:
            break
    assert info["laps"] >= 3 and len(info["lap_times"]) == info["laps"]
    assert info["lap_seconds"] == [round(t / 30, 6) for t in info["lap_times"]]
    assert sum(info["lap_times"]) <= info["step"] and 0 <= info["progress"] < 1
    first = laps_seen.index(1) + 1  # the step the first lap ended at
    assert info["lap_times"][0] == first
    obs, info = env.reset(seed=4)
    assert info["laps"] == 0 and info["lap_times"] == [] and info["crashes"] == 0


def test_the_vector_env_equals_single_envs_on_a_circuit():
    """The batched simulator (vector env) and the one-car path (single envs) agree step for step,
    laps and lap times included."""
    n = 3
    vector = RacingVectorEnv(n, track_file=example("kidney"), max_steps=400)
    singles = [gym.make("racing/Racing-v0", track_file=example("kidney"), max_steps=400) for _ in range(n)]
    obs, info = vector.reset(seed=7)
    np.testing.assert_array_equal(obs, np.stack([env.reset(seed=7 + i)[0] for i, env in enumerate(singles)]))
    rng = np.random.default_rng(0)
    for _ in range(399):
        actions = np.stack([ray_follower(o) for o in obs]) + rng.normal(0, 0.2, (n, 2))
        obs, reward, terminated, truncated, info = vector.step(actions)
        for i, env in enumerate(singles):
            o, r, te, tr, inf = env.step(actions[i])
            np.testing.assert_array_equal(obs[i], o)
            assert (reward[i], terminated[i], truncated[i]) == (r, te, tr)
            assert (info["laps"][i], info["lap_times"][i], info["crashes"][i]) == \
                (inf["laps"], inf["lap_times"], inf["crashes"])
    assert info["laps"].max() >= 1 and info["crashes"].max() >= 1


def test_a_circuit_resumes_exactly_mid_lap():
    track = load_track(example("oval"))
    config = track_config(track, racing.RacingConfig(max_steps=2000))
    sim = RacingSim(2, config=config, track=track)
    sim.seed([1, 2])
    sim.reset()
    follow = lambda s: np.array([ray_follower(o) for o in s.observe()])  # noqa: E731
    for _ in range(300):
        a = follow(sim)
        sim.step(a[:, 0], a[:, 1])
    assert sim.laps.min() >= 1
    state = sim.state_dict()
    again = RacingSim(2, config=config, track=track)
    again.load_state_dict(state)
    for _ in range(200):
        a, b = follow(sim), follow(again)
        np.testing.assert_array_equal(a, b)
        assert [np.array_equal(x, y) for x, y in zip(sim.step(a[:, 0], a[:, 1]), again.step(b[:, 0], b[:, 1]))] == \
            [True] * 4
    assert sim.lap_times == again.lap_times and (sim.laps == again.laps).all()
    with pytest.raises(ValueError, match="another track"):
        RacingSim(2, config=config, track=load_track(example("oval"), scale=1.5)).load_state_dict(state)


def test_training_on_a_file_track_records_the_file(tmp_path):
    from engine.config import ConfigError, RunConfig
    from engine.runner import train_population

    overrides = ["env.track=file", f"env.track_file={example('oval')}", "episodes=2", "progress=false",
                 "logger=none", "algo=spg", "er=recent", "algo.minibatch_size=100", "env.options.max_steps=100"]
    settings = RunConfig.compose_mapping(*overrides)
    summary = train_population(RunConfig.from_mapping(settings), tmp_path / "run", settings)[0]
    assert summary["status"] == "completed"
    assert summary["settings"]["env"]["track_file_sha256"] and summary["settings"]["env"]["track"] == "file"
    assert "track_file" not in RunConfig.compose_mapping()["env"]  # unset: not recorded (older runs match)
    changed = tmp_path / "oval.csv"
    changed.write_text(example("oval").read_text().replace("-500.000,0.000", "-500.000,0.001"))
    with pytest.raises(ConfigError, match="env.track=file needs env.track_file"):
        RunConfig.compose("env.track=file")
    with pytest.raises(ConfigError, match="not the file its run recorded"):
        RunConfig.from_mapping({**settings, "env": {**settings["env"], "track_file": str(changed)}})


def test_no_tool_writes_its_output_over_a_file_it_reads(tmp_path, capsys):
    """A table named as a run's track file (or as an input table) is refused in one line before any work: it
    would replace the circuit the run trained on."""
    import shutil

    import evaluate
    from analysis import compare, driving, pessimism, planner
    from engine.config import RunConfig
    from engine.runner import train_population

    track = tmp_path / "oval.csv"
    shutil.copy(example("oval"), track)
    settings = RunConfig.compose_mapping("env.track=file", f"env.track_file={track}", "episodes=1", "progress=false",
                                         "logger=none", "algo=spg", "er=recent", "env.options.max_steps=20",
                                         "algo.minibatch_size=20")
    train_population(RunConfig.from_mapping(settings), tmp_path / "sweep" / "run", settings)
    before = track.read_bytes()
    for tool in (driving.main, pessimism.main, planner.main, lambda a: evaluate.main(a)):
        with pytest.raises(SystemExit):
            tool([str(tmp_path / "sweep"), "--table", str(track)])
        err = capsys.readouterr().err
        assert f"--table {track} is the track file of the run" in err and "which this command reads" in err, err
    import score

    for args in ([str(tmp_path / "sweep" / "run")], ["ray_follower", "--laps-on", str(track)]):
        with pytest.raises(SystemExit):
            score.main([*args, "--table", str(track)])
        assert f"--table {track} is " in capsys.readouterr().err
    table = tmp_path / "runs.csv"
    table.write_text("x\n")
    with pytest.raises(SystemExit):
        compare.main([str(table), str(table), "--markdown", str(table)])
    assert "is an input file, which this command reads" in capsys.readouterr().err
    assert track.read_bytes() == before and table.read_text() == "x\n"


def test_the_documented_track_commands_run(tmp_path):
    commands = readme_commands("tracks.py")
    assert {c[0] for c in commands} >= {"check", "show", "export"}
    for args in commands:
        args = stand_in_circuits(args, tmp_path / "circuits")
        if "--out" in args:
            i = args.index("--out")
            args[i + 1] = str(tmp_path / Path(args[i + 1]).name)
        result = zygote.run(["tracks.py", *args], cwd=ROOT, env=ENV, timeout=120)
        assert result.returncode == 0, (shlex.join(args), result.stderr[-2000:])
        assert "checkpoints" in result.stdout
    bad = write(tmp_path, HEADER + "0,0,10,10\n")
    result = zygote.run(["tracks.py", "check", str(bad)], cwd=ROOT, env=ENV, timeout=120)
    assert result.returncode == 2 and "1 point(s); a track needs at least 3" in result.stderr


def test_a_figure_eight_is_refused_with_why_and_shown_with_its_crossing(tmp_path, capsys):
    """A circuit whose centre line crosses itself (a bridge, as Suzuka's) was refused by every tool with no
    word of why, and tracks.py show would not draw it: the refusal now says why such a circuit cannot be a
    track here, and show draws the refused file with the crossing marked (status 2: the file is refused)."""
    import tracks

    t = np.linspace(0, 2 * np.pi, 240, endpoint=False)
    rows = np.stack([600 * np.sin(t), 300 * np.sin(2 * t), np.full_like(t, 5.0), np.full_like(t, 5.0)], axis=1)
    path = tmp_path / "eight.csv"
    path.write_text("# x_m,y_m,w_tr_right_m,w_tr_left_m\n" + "\n".join(",".join(f"{v:.4f}" for v in r) for r in rows))
    with pytest.raises(TrackFileError, match="a circuit that passes over itself") as refused:
        load_track(path)
    assert "the walls cross themselves" in str(refused.value)
    pytest.importorskip("matplotlib", reason="drawing needs the render extra")
    assert tracks.main(["show", str(path), "--out", str(tmp_path / "eight.png")]) == 2
    out, err = capsys.readouterr()
    assert (tmp_path / "eight.png").stat().st_size > 0 and "crossing marked in red" in out
    assert len(err.strip().splitlines()) == 1 and "figure-eight" in err
