"""Real circuits as they are downloaded (racing/track_file.py): a file in the TUM
racetrack-database's layout (metres, closed, its first point not repeated, no settings comments)
is read as a circuit at the scale that gives its road a generated track's width; what the car may
not fit is said; laps end episodes; every tool takes the same overrides; the oracle's memory is
the track in use. The circuits are the project's own (``make_circuit``), in that layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import racing
from engine.config import ConfigError, RunConfig
from racing.sim import RacingSim
from racing.track_file import (FileTrack, TrackFileError, env_keywords, example, load_track, make_circuit,
                               parse_track, track_config, write_rows)
from tests.test_train import ENV, ROOT
from tests import zygote


@pytest.fixture(scope="module")
def circuit(tmp_path_factory) -> Path:
    """300 points 5 m apart, a road of 10 to 13 m: a small real circuit's file."""
    return write_rows(tmp_path_factory.mktemp("circuits") / "bean.csv", make_circuit(300))


def test_a_downloaded_layout_reads_as_a_circuit_the_car_fits_on(circuit):
    text = circuit.read_text()
    assert text.startswith("# x_m,y_m,w_tr_right_m,w_tr_left_m\n") and "closed" not in text and "scale" not in text
    rows = np.loadtxt(circuit, delimiter=",", comments="#")
    assert 4.9 < np.hypot(*(rows[-1, :2] - rows[0, :2])) < 5.1  # one segment from the first, not repeated
    track = load_track(circuit)
    r = track.reading
    assert track.closed and track.num_checkpoints == 300
    assert (r.closed_from, r.scale_from, r.warnings) == ("the geometry", "the road's width", ())
    widths = np.hypot(*(track.left_wall - track.right_wall).T)
    assert np.median(widths) == pytest.approx(200, rel=1e-3)  # a generated track's road
    assert r.scale == pytest.approx(200 / np.median(rows[:, 2] + rows[:, 3]), rel=1e-3)
    assert r.record() == {"file": str(circuit), "scale": r.scale, "scale_from": "the road's width", "closed": True,
                          "closed_from": "the geometry", "warnings": []}


def test_the_caller_beats_the_file_and_the_file_beats_the_rules(tmp_path, circuit):
    track = load_track(circuit, scale=1.0, closed=False)
    r = track.reading
    assert not track.closed and track.num_checkpoints == 299
    assert (r.scale, r.scale_from, r.closed_from) == (1.0, "the caller", "the caller")
    assert len(r.warnings) == 4  # a road and checkpoints narrower than a step, bends tighter than a turn, advice
    assert "narrower than a step at full speed (50 px)" in r.warnings[0]
    assert "skips it and counts as leaving the track" in r.warnings[1]
    assert "tighter than the car turns at any speed (75 px)" in r.warnings[2]
    commented = tmp_path / "commented.csv"
    commented.write_text("# closed: false\n# scale: 20\n" + circuit.read_text())
    r = load_track(commented).reading
    assert (r.closed, r.closed_from, r.scale, r.scale_from) == (False, "the file", 20.0, "the file")
    repeated = tmp_path / "repeated.csv"  # the first point written again at the end: a circuit too
    rows = make_circuit(40)
    write_rows(repeated, np.vstack([rows, rows[:1]]))
    assert load_track(repeated).closed and load_track(repeated).num_checkpoints == 40
    u_turn = tmp_path / "u.csv"  # an open track whose ends are far apart
    u_turn.write_text("".join(f"{x},{y},2,2\n" for x, y in [(0, 0), (0, 10), (0, 20), (10, 28), (20, 30), (30, 28),
                                                                   (40, 20), (40, 10), (40, 0)]))
    assert not load_track(u_turn).closed and load_track(u_turn).reading.closed_from == "the geometry"


def test_laps_end_an_episode_on_a_circuit_and_only_there():
    from racing.driver import PurePursuit

    track = load_track(example("oval"))
    for cars in (1, 3):  # the one-car path and the batched path
        config = track_config(track, racing.RacingConfig(laps=1, max_steps=1000))
        sim = RacingSim(cars, None, config, track=track)
        sim.seed(0)
        sim.reset()
        driver, ends = PurePursuit(), None
        for step in range(1, 1001):
            actions = np.array([driver.act(sim, c) for c in range(cars)])
            _, terminated, truncated, _ = sim.step(actions[:, 0], actions[:, 1])
            assert not truncated.any()
            if terminated.any():
                ends = step
                break
        assert ends is not None and sim.laps[int(np.flatnonzero(terminated)[0])] == 1
    with pytest.raises(ValueError, match="laps=2 ends an episode after laps of a circuit"):
        RacingSim(1, 2067791, racing.RacingConfig(laps=2))
    with pytest.raises(ValueError, match="laps must be an integer >= 0"):
        racing.RacingConfig(laps=-1)


@pytest.mark.slow
def test_every_tool_takes_the_same_overrides(tmp_path, circuit):
    track = parse_track("--track", str(circuit), 15.0, True)
    assert track == FileTrack(str(circuit), 15.0, True) and str(track) == str(circuit)
    assert env_keywords(track) == {"track_file": str(circuit), "track_scale": 15.0, "track_closed": True}
    env = racing.RacingEnv(**env_keywords(track))
    assert env.unwrapped.sim.file_track.reading.scale == 15.0
    with pytest.raises(TrackFileError, match="apply to a track file"):
        parse_track("--track", "2067791", 15.0, None)
    for command in (["tracks.py", "check", str(circuit), "--track-scale", "15", "--track-open", "--no-lap"],
                    ["score.py", "ray_follower", "--video", str(tmp_path / "a.gif"), "--video-track", str(circuit),
                     "--track-scale", "15", "--max-steps", "3"],
                    ["evaluate.py", "ray_follower", "--video", str(tmp_path / "b.gif"), "--track-file", str(circuit),
                     "--track-scale", "15"]):
        result = zygote.run(command, cwd=ROOT, env=ENV, timeout=300)
        assert result.returncode == 0, (command, result.stderr[-2000:])
        if command[0] == "tracks.py":
            assert "read as open (from the caller), scale 15 px per file unit (from the caller)" in result.stdout
    bad = zygote.run(["score.py", "ray_follower", "--video", str(tmp_path / "c.gif"), "--track-scale", "15"],
                     cwd=ROOT, env=ENV, timeout=300)
    assert bad.returncode == 2 and "apply to a --video-track or --laps-on file" in bad.stderr


def test_tracks_check_says_how_a_file_was_read_and_how_long_a_lap_takes(circuit):
    result = zygote.run(["tracks.py", "check", str(circuit)], cwd=ROOT, env=ENV, timeout=300)
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "a circuit (closed), 300 checkpoints" in out and "(median 200)" in out
    assert "read as a circuit (from the geometry), scale" in out and "(from the road's width)" in out
    assert "a lap: " in out and "for the pure-pursuit driver" in out and "for the ray-follower driver" in out
    assert "env.options.laps=1" in out and "warning" not in out
    narrow = zygote.run(["tracks.py", "check", str(circuit), "--track-scale", "1", "--no-lap"], cwd=ROOT, env=ENV,
                        timeout=300)
    assert narrow.returncode == 0 and narrow.stdout.count("warning:") == 4, narrow.stdout


def test_a_run_on_a_circuit_records_how_its_file_was_read(tmp_path, circuit):
    from engine.runner import train_population

    overrides = ["env.track=file", f"env.track_file={circuit}", "env.track_scale=16", "episodes=2",
                 "progress=false", "logger=none", "algo=spg", "er=recent", "algo.minibatch_size=100",
                 "env.options.max_steps=100", "eval_seeds=[1001]", "eval_episodes=1"]
    settings = RunConfig.compose_mapping(*overrides)
    assert settings["env"]["track_scale"] == 16 and "track_closed" not in settings["env"]  # unset: not recorded
    summary = train_population(RunConfig.from_mapping(settings), tmp_path / "run", settings)[0]
    assert summary["status"] == "completed"
    assert summary["track_file"] == {"file": str(circuit), "scale": 16.0, "scale_from": "the caller", "closed": True,
                                     "closed_from": "the geometry", "warnings": []}
    assert "own_track" in summary["evaluation"]
    for bad, message in ((["env.track_scale=2"], "say how to read env.track_file"),
                         (["env.track=file", f"env.track_file={circuit}", "env.track_scale=-1"], "must be a number > 0"),
                         (["env.track=file", f"env.track_file={circuit}", "env.track_closed=maybe"], "env.track_closed must be true")):
        with pytest.raises(ConfigError, match=message):
            RunConfig.compose(*bad)


def test_the_oracle_holds_only_the_driven_track(tmp_path):
    """A 1,200-checkpoint circuit: the planning cars share that track's tables, nothing else (they
    once started on random tracks of as many checkpoints each: 3.5 GB and a minute before the
    first step; speed/oracle_circuit.py prints the figures)."""
    from racing.oracle import Oracle, OracleSettings

    path = write_rows(tmp_path / "long.csv", make_circuit(1200))
    env = racing.RacingEnv(track_file=str(path))
    env.reset(seed=0)
    oracle = Oracle(OracleSettings(candidates=16, horizon=5, iterations=1), seed=0)
    assert oracle.planner is None  # nothing planned, nothing built
    env.step(oracle.act(env.unwrapped.sim, 0))
    bank = oracle.planner.bank
    assert [t for t in bank.tracks if t is not None] == [env.unwrapped.sim.file_track]
    assert bank.rays.shape[-1] == 1200  # one track's rows


def test_score_times_laps_on_a_circuit(tmp_path, circuit, capsys):
    import score

    table = tmp_path / "laps.csv"
    assert score.main(["ray_follower", "--laps-on", str(circuit), "--laps", "2", "--table", str(table)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("bean.csv: ray_follower: 2 of 2 laps in ") and "best lap " in line, line
    row = table.read_text().splitlines()[1].split(",")
    assert row[:5] == ["ray_follower", "reference (observation only)", str(circuit), "2", row[4]] and float(row[4]) > 0
    with pytest.raises(SystemExit):
        score.main(["ray_follower", "--laps-on", "2067791"])
    assert "--laps-on needs a track file (a circuit), got the seed 2067791" in capsys.readouterr().err


def test_score_says_one_line_for_a_raising_agent_and_na_for_one_track(tmp_path, monkeypatch, capsys):
    import score

    (tmp_path / "raiser.py").write_text("def act(observation):\n    return 1 / 0\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert score.main(["raiser:act", "--tracks", "1001", "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "score: raiser:act: the agent raised ZeroDivisionError: division by zero", err
    assert score.main(["ray_follower", "--tracks", "1001", "--episodes", "1"]) == 0
    assert "[n/a: one track] over 1 track x 1 episodes" in capsys.readouterr().out


def test_absurd_scales_and_damaged_files_are_refused_in_one_line(tmp_path, circuit):
    """A scale a thousand times too big or too small for float geometry, a flipped byte, a device."""
    with pytest.raises(TrackFileError, match=r"makes the track .* px across; at most 1e\+09"):
        load_track(circuit, scale=1e300)
    with pytest.raises(TrackFileError, match=r"below 0.001 px \(too small to compute walls on\); give a larger"):
        load_track(circuit, scale=1e-300)
    with pytest.raises(ConfigError, match="makes the track"):
        RunConfig.compose("env.track=file", f"env.track_file={circuit}", "env.track_scale=1e300")
    lines = circuit.read_text().splitlines()
    lines[100] = lines[100].replace(".", "x", 1)  # a flipped byte in a number
    damaged = tmp_path / "damaged.csv"
    damaged.write_text("\n".join(lines) + "\n")
    with pytest.raises(TrackFileError, match="line 101: x_m is .*, not a number"):
        load_track(damaged)
    with pytest.raises(TrackFileError, match="not a regular file"):
        parse_track("--laps-on", "/dev/zero")


def test_train_notes_what_the_car_cannot_fit_and_a_run_that_never_learns(monkeypatch, capsys, circuit):
    import engine.config

    monkeypatch.setattr(engine.config, "_noted", set())
    RunConfig.compose("env.track=file", f"env.track_file={circuit}", "env.track_scale=1", "algo=sac", "episodes=2")
    err = capsys.readouterr().err
    assert f"Note: env.track_file {circuit}: the road is" in err and "narrower than a step at full speed" in err
    assert "Note: algo.td.warmup_episodes=5 with episodes=2: no gradient step is taken" in err
    RunConfig.compose("env.track=file", f"env.track_file={circuit}", "algo=sac", "episodes=6")
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("Note:")]
    assert not [n for n in notes if "the road is" in n or "no gradient step" in n], notes  # auto scale fits; 6 > 5
    # what a run on a circuit says besides: the default 200 steps cover part of a lap; warm-up episodes among
    # the final performance's; thousands of random steps when episodes are long
    assert any(f"env.track_file {circuit}: an episode of 200 steps covers at most" in n and "of a lap even at "
               "full speed" in n and "env.options.max_steps=" in n for n in notes), notes
    assert any("the final performance averages the last 6 episodes, 5 of them warm-up episodes" in n for n in notes)
    RunConfig.compose("env.track=file", f"env.track_file={circuit}", "algo=sac", "env.options.max_steps=3600")
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("Note:")]
    assert "Note: algo.td.warmup_episodes=5 of 3,600 steps: 18,000 steps of uniform random actions before the " \
           "first gradient step (the default 5 episodes are 1,000 steps at 200 an episode)" in notes
    assert not any("covers at most" in n for n in notes), notes  # 3,600 steps reach round the lap
