"""The benchmark protocol and its commands (benchmark/protocol.py, score.py, drive.py): fixed unseen
tracks, every kind of agent, videos of any agent, and driving it yourself (headless)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from benchmark.protocol import TRACKS, AgentError, load_agent, read_oracle, score, summarise
from racing.track_file import example
from tests.test_readme import readme_commands, stand_in_circuits
from tests.test_train import ROOT


def test_the_benchmark_tracks_are_drawn_as_stated_and_named_nowhere_else():
    assert list(TRACKS) == [int(s) for s in np.random.SeedSequence(20261201).generate_state(10)]
    assert set(read_oracle()) == set(TRACKS)  # the oracle's scores ship for every one
    pages = [p for folder in ("conf", "docs", "analysis", "tests", "learners", "engine", "racing")
             for p in (ROOT / folder).rglob("*") if p.suffix in (".yaml", ".md", ".csv", ".py")]
    allowed = {ROOT / "engine" / "benchmark.py", ROOT / "analysis" / "data" / "oracle_benchmark.csv",
               ROOT / "docs" / "benchmark.md", Path(__file__)}
    for path in pages:
        if path in allowed or (ROOT / "docs" / "results" / "benchmark") in path.parents:  # its own results
            continue
        text = path.read_text(errors="replace")
        named = [t for t in TRACKS if re.search(rf"\b{t}\b", text)]
        assert not named, f"{path} names benchmark tracks {named}: they must stay unseen by every default and test"


def test_every_kind_of_agent_loads_and_bad_ones_are_refused_clearly(tmp_path, monkeypatch):
    (tmp_path / "my_driver.py").write_text("def drive(observation):\n    return [1.0, 0.0]\n"
                                           "def broken(observation):\n    return [1.0]\n")
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert load_agent("my_driver:drive").kind == "callable"
    assert load_agent("ray_follower").kind == "reference (observation only)"
    assert load_agent("pure_pursuit").kind == "reference (true state)"
    with pytest.raises(AgentError, match="cannot import module 'no_such_module'"):
        load_agent("no_such_module:drive")
    with pytest.raises(AgentError, match="has no callable 'missing'"):
        load_agent("my_driver:missing")
    with pytest.raises(AgentError, match="names no agent: give a train.py run folder"):
        load_agent("nothing")
    with pytest.raises(AgentError, match="holds no finished run"):
        load_agent(str(tmp_path))
    (tmp_path / "model.zip").write_bytes(b"not a zip")
    with pytest.raises(AgentError, match="is not a Stable-Baselines3 model.zip"):
        load_agent("model.zip")
    with pytest.raises(ValueError, match=r"action has shape \(1,\), expected \(2,\)"):
        score(load_agent("my_driver:broken"), TRACKS[:1], 1)


def test_a_stable_baselines3_model_zip_is_scored(tmp_path):
    import gymnasium as gym
    from stable_baselines3 import PPO, SAC

    import racing  # noqa: F401 (registers the environment)

    for kind in (SAC, PPO):
        model = kind("MlpPolicy", gym.make("racing/Racing-v0", track_seed=1), device="cpu", seed=0)
        model.save(tmp_path / f"{kind.__name__}.zip")
        agent = load_agent(str(tmp_path / f"{kind.__name__}.zip"))
        assert agent.kind == f"Stable-Baselines3 {kind.__name__}"
        assert np.isfinite(score(agent, TRACKS[:1], 1)[TRACKS[0]])


def test_score_py_prints_raw_and_normalised_scores_with_intervals(tmp_path, capsys):
    import score as score_py

    table = tmp_path / "scores.csv"
    assert score_py.main(["ray_follower", "racing.driver:ray_follower", "--episodes", "1", "--tracks",
                          *map(str, TRACKS[:3]), "--table", str(table)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("note: 3 tracks x 1 episodes is not the benchmark's protocol (10 x 5)")
    pattern = r"ray_follower \(.*\): score [\d.]+ \[[\d.]+, [\d.]+\] over 3 tracks x 1 episodes; " \
              r"oracle-normalised 0\.\d{3} \[0\.\d{3}, [01]\.\d{3}\]"
    assert re.match(pattern, lines[1]) and re.match("racing.driver:" + pattern, lines[2])
    assert lines[1].split(": score")[1] == lines[2].split(": score")[1]  # the same driver, the same numbers
    rows = table.read_text().splitlines()
    assert rows[0] == "agent,kind,track,episodes,mean_reward,oracle,normalised" and len(rows) == 7
    per_track = {TRACKS[i]: float(rows[1 + i].split(",")[4]) for i in range(3)}
    summary = summarise(per_track, read_oracle())
    assert f"score {summary['mean']:.1f}" in lines[1]
    with pytest.raises(SystemExit) as refused:
        score_py.main(["ray_follower", "--tracks", "-1"])
    assert refused.value.code == 2 and "argument --tracks: must be in [0, 4,294,967,295]" in capsys.readouterr().err


@pytest.mark.slow
def test_any_agent_is_filmed_on_a_seed_or_a_file_track(tmp_path, capsys):
    import evaluate
    import score as score_py

    assert score_py.main(["pure_pursuit", "racing.driver:ray_follower", "--video", str(tmp_path / "drive.gif"),
                          "--video-track", str(example("oval")), "--max-steps", "12"]) == 0
    assert "wrote " + str(tmp_path / "drive-0.gif") + ": pure_pursuit on track" in capsys.readouterr().out
    import imageio.v2 as imageio

    for n in (0, 1):
        frames = imageio.mimread(tmp_path / f"drive-{n}.gif")
        assert len(frames) == 13 and frames[0].shape[:2] == (600, 600)
    assert evaluate.main(["racing.driver:ray_follower", "--video", str(tmp_path / "follower.mp4"),
                          "--track-file", str(example("kidney"))]) == 0  # evaluate.py films any agent too
    assert f"wrote {tmp_path / 'follower.mp4'} (201 frames)" in capsys.readouterr().out
    from benchmark.protocol import film

    frames, total = film(load_agent("oracle"), TRACKS[0], tmp_path / "oracle.gif", max_steps=6)
    assert frames == 7 and total > 0


def test_a_run_trained_on_a_file_track_is_filmed_and_scored(tmp_path, capsys):
    from engine.config import RunConfig
    from engine.runner import train_population

    overrides = ["env.track=file", f"env.track_file={example('kidney')}", "episodes=2", "progress=false",
                 "logger=none", "algo=spg", "er=recent", "algo.minibatch_size=50", "env.options.max_steps=50"]
    settings = RunConfig.compose_mapping(*overrides)
    train_population(RunConfig.from_mapping(settings), tmp_path / "run", settings)
    import evaluate

    assert evaluate.main([str(tmp_path / "run"), "--episodes", "1", "--video", str(tmp_path / "run.gif")]) == 0
    out = capsys.readouterr().out
    assert f"track {example('kidney')}: mean total reward" in out and "(51 frames)" in out
    agent = load_agent(str(tmp_path / "run"))
    assert agent.kind == "run folder" and np.isfinite(score(agent, TRACKS[:1], 1)[TRACKS[0]])


def test_driving_yourself_headless_with_scripted_keys(monkeypatch, capsys):
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    import drive

    assert drive.action_of({"up", "left"}) == [1.0, 1.0] and drive.action_of({"down", "right"}) == [-1.0, -1.0]
    assert drive.action_of(set()) == [0.0, 0.0]
    still = drive.play(str(example("oval")), max_steps=30, fps=10000, oracle=False, script={})
    totals = drive.play(str(example("oval")), ghost=load_agent("ray_follower"), max_steps=30, fps=10000,
                        oracle=True, script={0: [("up", True)], 20: [("up", False), ("down", True)]})
    assert totals["you"] > still["you"] > 0  # full throttle beats holding a target of half speed
    assert totals["ghost"] > 0 and totals["oracle"] > 0
    assert f"you: {totals['you']:.1f}; ghost (ray_follower): {totals['ghost']:.1f}; oracle:" in capsys.readouterr().out


def test_driving_without_a_display_ends_in_one_line_at_once(monkeypatch, capsys):
    """Without a display drive.py printed SDL's warning, drove an invisible episode and waited for a key
    that could never come; now it ends at once, in one line, with status 2 (SDL_VIDEODRIVER set: the
    user's choice, as the tests' dummy driver)."""
    import drive

    for key in ("SDL_VIDEODRIVER", "DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(key, raising=False)
    assert drive.main(["--max-steps", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("drive: no display to open a window on") and "score.py" in err[0]
    assert drive.display_problem({"DISPLAY": ":0"}, "linux") is None
    assert drive.display_problem({"SDL_VIDEODRIVER": "dummy"}, "linux") is None
    assert drive.display_problem({}, "darwin") is None and drive.display_problem({}, "linux")


def test_the_documented_benchmark_commands_run(tmp_path, monkeypatch, capsys):
    """Every python score.py / drive.py line of the README and docs/, at a tiny size."""
    import drive
    import score as score_py

    score_lines, drive_lines = readme_commands("score.py"), readme_commands("drive.py")
    assert score_lines and drive_lines
    for args in score_lines:
        args = stand_in_circuits(_tiny_paths(args, tmp_path), tmp_path / "circuits")
        if "--laps-on" in args:
            args += ["--laps", "1", "--max-steps", "5"]
        elif "--video" in args:
            args += ["--max-steps", "5"]
        elif not any(a == "--tracks" for a in args):
            args += ["--episodes", "1", "--tracks", str(TRACKS[0])]
        assert score_py.main(args) == 0, shlex.join(args)
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    for args in drive_lines:
        args = stand_in_circuits(args, tmp_path / "circuits")
        args = [a for a in args if a != "--no-oracle"] + ["--fps", "10000", "--max-steps", "5", "--no-oracle"]
        capsys.readouterr()
        assert drive.main(args) == 0, shlex.join(args)
        assert capsys.readouterr().out.startswith("you: ")


def _tiny_paths(args: list[str], tmp_path: Path) -> list[str]:
    args = list(args)
    for option in ("--table", "--video"):
        if option in args:
            i = args.index(option)
            args[i + 1] = str(tmp_path / Path(args[i + 1]).name)
    return args


@pytest.mark.slow
def test_the_leaderboard_scores_every_run_of_a_sweep_beside_the_references(tmp_path, capsys):
    """python -m benchmark.leaderboard on a tiny sweep: one agent per cell, its runs and tracks
    resampled for the interval; a diverged run is left out and named."""
    from benchmark import leaderboard
    from engine.config import RunConfig
    from engine.runner import train_population

    for overrides in (["algo=spg", "er=recent", "seeds=[1,2]"], ["algo=ppo_log", "er=recent", "seed=3",
                                                                 "algo.critic_lr=1e30"]):
        settings = RunConfig.compose_mapping(*overrides, "env.track=random", "episodes=2", "progress=false",
                                             "logger=none", "algo.minibatch_size=50")
        name = overrides[0].split("=")[1]
        train_population(RunConfig.from_mapping(settings), tmp_path / "sweep" / name, settings)
    assert leaderboard.main([str(tmp_path / "sweep"), "--out", str(tmp_path / "board")]) == 0
    out, err = capsys.readouterr()
    board = (tmp_path / "board" / "leaderboard.md").read_text()
    assert board.splitlines()[0] == "| agent | runs | score [95% interval] | oracle-normalised [95% interval] |"
    assert "| SPG, recent | 2 |" in board and "| reference: oracle | 1 | 165.9 [" in board
    assert "| reference: ray follower | 1 | 133.4 [125.6, 141.8] | 0.803 [0.77" in board  # score.py's numbers
    assert "skipped" in err and "ppo_log" in err  # the diverged run has no policy
    assert len((tmp_path / "board" / "runs.csv").read_text().splitlines()) == 1 + 10 * 4
    preset = RunConfig.compose("+experiment=benchmark", "+cell=memory-sac")  # the leaderboard's sweep
    assert preset.env.track == "random" and preset.seeds == (1, 2, 3) and preset.algo.name == "sac"
    scores = np.array([[1.0, 2.0], [3.0, 4.0]])
    mean, low, high = leaderboard.interval(scores)
    assert mean == 2.5 and 1.0 <= low < mean < high <= 4.0


def test_the_end_screen_stays_until_the_window_is_closed(monkeypatch):
    """drive.py's end screen waits for the window's close (here posted 0.5 s later from a timer)."""
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    import threading
    import time

    import drive
    from racing.render import import_pygame

    pg = import_pygame()
    closer = threading.Timer(0.5, lambda: pg.event.post(pg.event.Event(pg.QUIT)))
    start = time.perf_counter()
    closer.start()
    drive.play(str(example("oval")), max_steps=3, fps=10000, oracle=False, hold=True)
    assert time.perf_counter() - start >= 0.5


@pytest.mark.slow
def test_the_documented_board_from_committed_scores(tmp_path):
    """docs/benchmark.md's ``--scores`` line: the committed boards' scores in one board, with the agents as
    rliable reports them; every row of the committed leaderboard comes out the same from its scores."""
    from benchmark import leaderboard

    lines = [a for a in readme_commands("-m benchmark.leaderboard") if "--scores" in a]
    assert lines
    for args in lines:
        args = args[:args.index("--out")] + ["--out", str(tmp_path)]
        assert leaderboard.main(args) == 0
    board = (tmp_path / "leaderboard.md").read_text().splitlines()
    committed = (ROOT / "docs" / "results" / "benchmark" / "leaderboard.md").read_text().splitlines()
    assert set(committed) <= set(board)  # the same scores, the same intervals
    statistics = (tmp_path / "statistics.md").read_text()
    assert "| SPG-p, multiple epochs, memory | 3 |" in statistics and "(ref)" in statistics
    assert "| NAF, memory | 3 |" in statistics and "| reference: oracle | 1 | 1.000 | 1.000 | 0.000 |" in statistics
    assert (tmp_path / "profiles.png").stat().st_size > 0  # the render extra is in the dev install


@pytest.mark.slow
def test_an_mp4_keeps_its_frames_and_a_circuit_film_ends_at_its_laps(tmp_path, capsys, recwarn):
    """An .mp4 printed imageio's macro_block_size warning and resized its frames; frames now keep their
    size, padded with their own edge; ``--laps`` ends a film on a circuit, and its line gives the size."""
    import warnings

    import score as score_py
    from engine.evaluation import _padded, write_video

    frame = np.arange(30 * 50 * 3, dtype=np.uint8).reshape(30, 50, 3)
    padded = _padded(frame, 16)
    assert padded.shape == (32, 64, 3) and (padded[:30, :50] == frame).all() and (padded[31, 60] == frame[29, 49]).all()
    pytest.importorskip("imageio_ffmpeg", reason="mp4 needs the render extra's ffmpeg")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert write_video([frame] * 3, tmp_path / "a.mp4") == 3
    circuit = str(example("oval"))
    assert score_py.main(["pure_pursuit", "--video", str(tmp_path / "lap.gif"), "--video-track", circuit,
                          "--laps", "1", "--max-steps", "5000"]) == 0
    out = capsys.readouterr().out
    frames = int(out.split(" frames")[0].split(", ")[-1])
    assert 1 < frames < 5000 and " MB), total reward" in out  # the lap ended it, long before the step cap
    assert score_py.main(["pure_pursuit", "--video", str(tmp_path / "x.gif"), "--laps", "1"]) == 2
    assert "laps=1 ends an episode after laps of a circuit; these cars drive" in capsys.readouterr().err


def _scores_file(path: Path, agents: dict[str, float], episodes: dict[str, int] | None = None) -> Path:
    """A leaderboard's runs.csv: each agent one run scoring ``value`` on every benchmark track."""
    import csv

    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["agent", "run", "track", "mean_reward", "normalised"] + (["episodes"] if episodes else []))
        for agent, value in agents.items():
            for track in TRACKS:
                writer.writerow([agent, f"runs/{agent}", track, value, ""] + ([episodes[agent]] if episodes else []))
    return path


def test_a_board_from_scores_refuses_what_no_run_can_score_and_escapes_names(tmp_path, capsys):
    """--scores checks scores as report.py checks finals (finite, within what an episode totals), refuses
    one run's two scores of a track naming both files, refuses names a table cannot hold, escapes the
    rest; a board of agents trained for different budgets says so under its table."""
    from benchmark import leaderboard

    def refused(*paths: Path) -> str:
        assert leaderboard.main(["--scores", *map(str, paths), "--out", str(tmp_path / "board")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1
        return err[0]

    for value in ("nan", "inf", "1e9", "-2000.5", "200.01"):
        line = refused(_scores_file(tmp_path / "bad.csv", {"SAC": value}))
        assert "bad.csv line 2" in line and ("not a finite number in [-2000, 200]" in line or "is not a number" in line)
    assert not (tmp_path / "board").exists()
    first = _scores_file(tmp_path / "one.csv", {"SAC": 140.0})
    line = refused(first, _scores_file(tmp_path / "two.csv", {"SAC": 141.0}))
    assert "one.csv line 2" in line and "two.csv line 2" in line and "one run has one score per track" in line
    assert "control characters" in refused(_scores_file(tmp_path / "bad.csv", {"SAC\n| x | 9 |": 140.0}))
    assert "at most 200" in refused(_scores_file(tmp_path / "bad.csv", {"S" * 201: 140.0}))

    again = _scores_file(tmp_path / "again.csv", {"SAC": 140.0})  # the same run's same scores: counted once
    odd = _scores_file(tmp_path / "odd.csv", {"a | b <i>": 120.0, "$x_{$": 100.0, "_hidden": 90.0},
                       episodes={"a | b <i>": 10, "$x_{$": 201, "_hidden": 201})
    assert leaderboard.main(["--scores", str(first), str(again), str(odd), "--out", str(tmp_path / "board")]) == 0
    table = (tmp_path / "board" / "leaderboard.md").read_text().splitlines()
    assert "| a \\| b &lt;i> | 1 | 120.0 [120.0, 120.0] |" in "\n".join(table)
    assert "| \\$x\\_{\\$ | 1 |" in "\n".join(table)
    assert all(line.replace("\\|", "").count("|") == 5 for line in table if line.startswith("|"))
    assert "| SAC | 1 |" in "\n".join(table)  # one run, not two
    assert table[-1].startswith("Note: these agents were trained for different budgets (10 episodes: a \\| b")
    assert (tmp_path / "board" / "profiles.png").stat().st_size > 0  # "$x_{$" drawn as text


def test_a_figure_of_many_agents_gives_each_coloured_line_its_own_colour():
    """profiles.png with 19 agents: the best six learned agents in six colours, the references dashed in
    dark tones, the rest grey under one legend entry."""
    from analysis.statistics import COLOURED, line_styles

    ranked = [f"agent {i}" for i in range(16)] + ["reference: oracle", "reference: ray follower",
                                                  "reference: pure pursuit"]
    styles = line_styles(ranked, lambda name: name.startswith("reference:"))
    coloured = [s["color"] for s in styles.values() if s["color"] != "0.72"]
    assert len(coloured) == len(set(coloured)) == COLOURED + 3
    grey = [name for name, s in styles.items() if s["color"] == "0.72"]
    assert grey == ranked[COLOURED:16]
    assert [styles[n]["label"] for n in grey] == ["10 other agents"] + [None] * 9
    assert all(styles[n]["linestyle"] == "--" for n in ranked[16:])


def test_a_board_from_scores_reads_only_what_a_leaderboard_writes(tmp_path, capsys):
    """Found by a hostile trial of the checks above: an agent named after a reference driver replaced it
    (the oracle) or stood as it (made-up ray follower scores); an agent starting with '#' vanished as a
    comment; duplicate or surplus columns, empty files, odd digits and names that format the page passed;
    --out wrote into a run folder; 30,000 runs of an agent asked for 22 GB."""
    from benchmark import leaderboard
    from tests.test_run_folders import TINY, train

    def result(*paths, out=tmp_path / "board"):
        code = leaderboard.main(["--scores", *map(str, paths), "--out", str(out)])
        return code, capsys.readouterr().err.strip().splitlines()

    def refused(*paths, out=tmp_path / "board") -> str:
        code, err = result(*paths, out=out)
        assert code == 2 and len(err) == 1, err
        return err[0]

    assert "takes a reference driver's name" in refused(_scores_file(tmp_path / "o.csv", {"reference: oracle": 100.0}))
    assert "begins as the board's own 'reference' names do" in refused(  # a Cyrillic е (engine.names)
        _scores_file(tmp_path / "cy.csv", {"r\u0435ference: ray follower": 150.0}))
    assert "a board takes at most 50" in refused(_scores_file(tmp_path / "many.csv", {f"a{i}": 100.0 for i in range(51)}))
    formula = _scores_file(tmp_path / "formula.csv", {"=HYPERLINK(1)": 100.0})
    assert result(formula)[0] == 0 and "'=HYPERLINK(1)" in (tmp_path / "board" / "runs.csv").read_text()
    assert result(tmp_path / "board" / "runs.csv", out=tmp_path / "again")[0] == 0  # reads back as written
    assert "| =HYPERLINK(1) |" in (tmp_path / "again" / "leaderboard.md").read_text()
    fake = _scores_file(tmp_path / "rf.csv", {"reference: ray follower": 150.0})
    fake.write_text(fake.read_text().replace("runs/reference: ray follower", "ray_follower"))
    assert "where the protocol gives it" in refused(fake)
    (tmp_path / "empty.csv").write_text("")
    assert "holds no scores" in refused(tmp_path / "empty.csv")
    (tmp_path / "header.csv").write_text("agent,run,track,mean_reward\n")
    assert "holds no scores" in refused(tmp_path / "header.csv")
    good = _scores_file(tmp_path / "good.csv", {"#1 agent": 120.0, "**b** [x](http://e) ![i](http://e/i.png)": 110.0})
    text = good.read_text()
    (tmp_path / "twice.csv").write_text(text.replace("mean_reward,normalised", "mean_reward,mean_reward", 1))
    assert "names column 'mean_reward' twice" in refused(tmp_path / "twice.csv")
    (tmp_path / "extra.csv").write_text(text.replace(",120.0,", ",120.0,,EXTRA,", 1))
    assert "more fields than its header" in refused(tmp_path / "extra.csv")
    for column, bad in (("track", "+30_11430478"), ("mean_reward", "1_0_0"), ("episodes", "\u00b2"), ("episodes", "9" * 20)):
        lines = (_scores_file(tmp_path / "odd.csv", {"A": 100.0}, episodes={"A": 7})).read_text().splitlines()
        header = lines[0].split(",")
        cells = lines[1].split(",")
        cells[header.index(column)] = bad
        (tmp_path / "odd.csv").write_text("\n".join([lines[0], ",".join(cells), *lines[2:]]) + "\n")
        assert "is not a number" in refused(tmp_path / "odd.csv"), (column, bad)
    assert "name is empty" in refused(_scores_file(tmp_path / "blank.csv", {"  ": 100.0}))
    many = tmp_path / "many.csv"
    many.write_text("agent,run,track,mean_reward\n" + "".join(f"A,r{r},{t},100\n" for r in range(1001) for t in TRACKS))
    assert "at most 1,000 runs of one agent" in refused(many)

    (tmp_path / "bom.csv").write_text("\ufeff" + text)  # as a spreadsheet saves it
    code, _ = result(tmp_path / "bom.csv")
    assert code == 0
    board = (tmp_path / "board" / "leaderboard.md").read_text()
    assert "| #1 agent | 1 | 120.0" in board  # not a comment
    assert "| \\*\\*b\\*\\* \\[x\\](http&#58;//e) \\!\\[i\\](http&#58;//e/i.png) | 1 |" in board
    written = (tmp_path / "board" / "runs.csv").read_text().splitlines()
    assert written[0] == "agent,run,track,mean_reward,normalised" and len(written) == 1 + 20

    run = tmp_path / "run"
    train([*TINY], run)
    with pytest.raises(SystemExit):
        leaderboard.main(["--scores", str(good), "--out", str(run / "board")])
    assert "is inside the run folder" in capsys.readouterr().err and not (run / "board").exists()


def test_the_interval_of_many_runs_is_taken_in_pieces():
    """The same numbers as in one piece, at a bounded size: 1,000 runs of ten tracks resampled 10,000 times took
    0.8 GB in one array."""
    from benchmark.leaderboard import interval

    scores = np.random.default_rng(3).normal(size=(40, 10))
    rng = np.random.default_rng(0)
    runs, tracks = rng.integers(0, 40, size=(10000, 40)), rng.integers(0, 10, size=(10000, 10))
    whole = scores[runs[:, :, None], tracks[:, None, :]].mean(axis=(1, 2))
    assert interval(scores)[1:] == tuple(float(x) for x in np.percentile(whole, [2.5, 97.5]))
