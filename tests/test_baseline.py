"""baseline.py: Stable-Baselines3's SAC and PPO with their defaults, written as run folders.

The command the docs show runs at a tiny size (one episode, one track): each run's folder has
the learning curve and a summary the report reads, a rerun of the same settings is skipped, the
same settings train the same curve again, and bad arguments are refused with a reason.
"""

import json

import pytest

from tests.test_readme import readme_commands
from tests import zygote
from tests.test_train import ENV, ROOT, read_rows

pytest.importorskip("stable_baselines3", reason="Stable-Baselines3 is the baselines extra (pip install -e '.[baselines]')")


def baseline(*args):
    return zygote.run([ROOT / "baseline.py", *args], cwd=ROOT, env=ENV, timeout=600)


def tiny(args: list[str], out) -> list[str]:
    """The documented command at one episode (SAC: 100 gradient steps) on its first track, into ``out``."""
    args = list(args)
    tracks = args.index("--tracks")
    end = next((i for i in range(tracks + 1, len(args)) if args[i].startswith("--")), len(args))
    args[tracks + 1:end] = [args[tracks + 1]]
    for flag in ("--episodes", "--out"):
        if flag in args:
            del args[args.index(flag):args.index(flag) + 2]
    return [*args, "--episodes", "1", "--out", str(out)]


@pytest.mark.slow
def test_the_documented_command_writes_runs_the_report_reads_and_reruns_identically(tmp_path):
    commands = [c for c in readme_commands("baseline.py", include_elsewhere=True) if "--random-tracks" not in c]
    assert commands, "the docs show no baseline.py command on fixed tracks"
    args = tiny(commands[0], tmp_path / "a")
    assert "sac" in args and "ppo" in args
    result = baseline(*args)
    assert result.returncode == 0, result.stderr[-3000:]
    track = args[args.index("--tracks") + 1]
    for algo in ("sac", "ppo"):
        folder = tmp_path / "a" / f"sb3_{algo}" / "default" / f"seed{track}"
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["episodes"] == 1 and summary["algo"] == f"sb3_{algo}"
        assert summary["software"]["stable_baselines3"] and summary["code"]["source"]
        assert summary["settings"]["sb3"]["gamma"] == 0.99
        assert [int(r["episode"]) for r in read_rows(folder / "metrics.csv")] == [0]
        assert (folder / "model.zip").exists()
    assert json.loads((tmp_path / "a" / "sb3_sac" / "default" / f"seed{track}" / "summary.json").read_text()
                      )["settings"]["sb3"]["net_arch"] == "[256, 256]"
    sac = tmp_path / "a" / "sb3_sac" / "default" / f"seed{track}" / "metrics.csv"
    written = sac.stat().st_mtime_ns
    assert baseline(*args).returncode == 0 and sac.stat().st_mtime_ns == written  # finished: skipped
    again = baseline(*tiny(["--algos", "sac", "--tracks", track], tmp_path / "b"))
    assert again.returncode == 0, again.stderr[-3000:]
    assert (tmp_path / "b" / "sb3_sac" / "default" / f"seed{track}" / "metrics.csv").read_bytes() == sac.read_bytes()
    report = zygote.run([ROOT / "report.py", tmp_path / "a"], cwd=ROOT, env=ENV, timeout=300)
    assert report.returncode == 0, report.stderr[-3000:]
    assert "sb3_sac" in (tmp_path / "a" / "report" / "runs.csv").read_text()
    assert "Stable-Baselines3 SAC, default" in (tmp_path / "a" / "report" / "beyond.md").read_text()


@pytest.mark.parametrize("args, message", [
    (["--algos", "td3", "--tracks", "1"], "algo must be one of sac, ppo"),
    (["--tracks", "1", "--episodes", "0"], "argument --episodes: must be in [1, 100,000], got 0"),
    (["--tracks", "-1"], "argument --tracks: must be in [0, 4,294,967,295], got -1"),
])
def test_bad_arguments_are_refused_with_a_reason(tmp_path, args, message):
    result = baseline(*args, "--out", str(tmp_path))
    assert result.returncode == 2 and message in result.stderr and "Traceback" not in result.stderr


@pytest.mark.slow
def test_random_tracks_train_on_a_new_track_each_episode_and_the_benchmark_scores_the_folder(tmp_path):
    """--random-tracks (the benchmark's training): the run's settings say so, its episodes differ
    from the same seed's fixed-track run, and score.py's agent loader takes the run folder."""
    from benchmark.protocol import load_agent

    documented = [c for c in readme_commands("baseline.py", include_elsewhere=True) if "--random-tracks" in c]
    assert documented, "docs/benchmark.md shows how the leaderboard's Stable-Baselines3 runs are made"
    # The documented command at a tiny size, with PPO for SAC (its episodes are cheaper; the algorithm
    # does not change what the option does) and a second episode (a second track).
    args = tiny(documented[0], tmp_path / "random")
    args[args.index("--algos") + 1:args.index("--tracks")] = ["ppo"]
    args[args.index("--tracks") + 1] = "7"
    args[args.index("--episodes") + 1] = "2"
    common = ["--algos", "ppo", "--tracks", "7", "--episodes", "2"]
    assert baseline(*common, "--out", str(tmp_path / "fixed")).returncode == 0
    result = baseline(*args)
    assert result.returncode == 0, result.stderr[-3000:]
    folder = tmp_path / "random" / "sb3_ppo" / "default" / "seed7"
    settings = json.loads((folder / "summary.json").read_text())["settings"]
    assert settings["track"] == "random"
    assert "track" not in json.loads((tmp_path / "fixed" / "sb3_ppo" / "default" / "seed7" / "summary.json")
                                     .read_text())["settings"]  # as runs before the option recorded them
    fixed = read_rows(tmp_path / "fixed" / "sb3_ppo" / "default" / "seed7" / "metrics.csv")
    assert read_rows(folder / "metrics.csv")[1] != fixed[1]  # the second episode is on another track
    agent = load_agent(str(folder))
    assert agent.kind == "Stable-Baselines3 PPO"
    # The leaderboard scores these beside this project's runs (fma) under fma: their torch layers
    # compute the same there as under portable, the mode they were trained in.
    from benchmark.leaderboard import _numerics
    from evaluate import runs_numerics
    from tests.test_train import run_train

    ours = tmp_path / "ours"
    assert run_train("algo=ppo", "er=recent", "episodes=1", "progress=false", f"hydra.run.dir={ours}").returncode == 0
    assert _numerics([folder], runs_numerics) == "portable"
    assert _numerics([ours, folder], runs_numerics) == "fma"
