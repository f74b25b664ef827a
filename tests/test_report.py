"""report.py: Table 1 from a sweep folder, tolerant of partial, damaged and diverged runs."""

import json
import math
import shutil

import pytest

import report
from analysis.report import cells, find_runs, read_paper_table


CODE = {"commit": "a" * 40, "dirty": False, "origin": "git", "source": "0123456789abcdef"}
PORTABLE = {"mode": "portable", "kernels": "AVX2", "mkl_branch": "COMPATIBLE"}


def write_summary(folder, data):
    """A summary as train.py writes it: its files' record and its own digest."""
    from engine.outputs import RECORDABLE_FILES, file_record, seal

    data = {**{k: v for k, v in data.items() if k != "sha256"}, "files": file_record(folder, RECORDABLE_FILES)}
    (folder / "summary.json").write_text(json.dumps(seal(data)))


def fake_run(root, algo, er, seed, final=None, status="completed", summary=True, episodes=3, code=CODE,
             numerics=PORTABLE, compiled=None):
    folder = root / algo / er / f"seed{seed}"
    folder.mkdir(parents=True)
    rows = ["episode,total_reward"] + [f"{i},{(final or 0.0) + i - 1}" for i in range(episodes)]
    (folder / "metrics.csv").write_text("\n".join(rows) + "\n")
    if summary is True:
        if status == "completed":  # a finished run's weights (engine.rundir checks they are there)
            for name in ("model.zip",) if algo.startswith("sb3_") else ("actor.pt", "critic.pt"):
                (folder / name).write_bytes(b"weights")
        write_summary(folder, {
            "algo": algo, "er": er, "seed": seed, "final_mean": final, "status": status, "episodes": episodes,
            "code": code, **({"numerics": numerics} if numerics else {"software": {"cpu": "AVX2"}}),
            **({"compile": {"requested": compiled, "enabled": compiled, "reason": None}} if compiled is not None
               else {}), "settings": {"env": {"track": "fixed"}}})
    elif summary:
        (folder / "summary.json").write_text(summary)
    return folder


def test_paper_table_is_in_the_project():
    paper = read_paper_table()
    assert len(paper) == 15
    assert paper[("memory", "spg_p_multi")] == (141.1, 5.7)
    assert paper[("hybrid", "spg_multi")] == (140.9, 4.0)
    assert ("hybrid", "ppo_log") not in paper


def test_cell_statistics_by_hand(tmp_path):
    for seed, final in zip(range(5), [100.0, 110.0, 120.0, 130.0, 140.0]):
        fake_run(tmp_path, "spg_p_multi", "memory", seed, final, episodes=201)
    (cell,) = [c for c in cells(find_runs(tmp_path), read_paper_table()) if c.n]
    sem = math.sqrt(250.0) / math.sqrt(5)  # sample sd of 100..140 is sqrt(250)
    assert (cell.mean, cell.sem) == (120.0, pytest.approx(sem))
    assert cell.z == pytest.approx((120.0 - 141.1) / math.hypot(sem, 5.7))


@pytest.mark.slow
def test_the_table_states_each_budget_and_compares_only_the_paper_s(tmp_path, capsys):
    """Runs of 20 episodes are not set against the paper's 201-episode values; a cell mixing budgets
    says so instead of averaging silently; one run has no spread (n/a, not nan); the conclusions
    pair runs of one budget; table.csv names each cell's budgets."""
    from analysis.report import conclusions_markdown

    for seed, final in zip((1, 2, 3), (30.0, 32.0, 34.0)):
        fake_run(tmp_path, "spg", "recent", seed, final, episodes=20)
    fake_run(tmp_path, "ppo", "recent", 1, 40.0, episodes=20)
    fake_run(tmp_path, "ppo", "recent", 2, 60.0, episodes=100)
    fake_run(tmp_path, "ppo", "recent", 3, 62.0, episodes=100)
    fake_run(tmp_path, "spg_p", "recent", 1, 20.0, episodes=20)
    table = {(c.er, c.algo): c for c in cells(find_runs(tmp_path), read_paper_table()) if c.n}
    spg, ppo, spg_p = table[("recent", "spg")], table[("recent", "ppo")], table[("recent", "spg_p")]
    assert spg.budgets == (20,) and spg.z is None and not spg.comparable
    assert ppo.budgets == (20, 100) and ppo.z is None
    assert report.main([str(tmp_path), "--no-figures"]) == 0
    out = capsys.readouterr().out
    assert "32.0 ± 1.2 (n=3; 20 episodes)<br>paper " in out and "at 201 episodes: not compared" in out
    assert "(n=3; mixed budgets: 20, 100 episodes)" in out
    assert "20.0 ± n/a (one run) (n=1; 20 episodes)" in out
    assert "Δ =" not in out and "nan" not in out
    assert "Runs of 20, 100 episodes are not compared with the paper's values" in out
    assert "Cells averaging runs of different budgets (their mean is of unlike runs): recent / PPO linear." in out
    assert (tmp_path / "report" / "table.csv").read_text().splitlines()[0].endswith(",z,episodes")
    conclusions = conclusions_markdown(find_runs(tmp_path))
    assert "The effects pair runs of 20 episodes only: 2 finished run(s) of other budgets (100 episodes)" in conclusions
    assert "nan" not in conclusions


def test_report_lists_partial_damaged_and_diverged_runs(tmp_path, capsys):
    fake_run(tmp_path, "spg", "recent", 1, 90.0)
    fake_run(tmp_path, "spg", "recent", 2, 100.0)
    fake_run(tmp_path, "ppo_log", "hybrid", 1, None, status="diverged")
    fake_run(tmp_path, "spg", "recent", 3, summary=False)
    fake_run(tmp_path, "spg", "recent", 4, summary="{not json")
    fake_run(tmp_path, "spg", "recent", 5, summary="[1, 2]")  # JSON, but not a summary
    (fake_run(tmp_path, "spg", "recent", 6, 120.0) / "actor.pt").write_bytes(b"")  # a finished run's file emptied
    assert report.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "1 diverged run(s)" in out and "1 partial run(s)" in out and "3 damaged run(s)" in out
    assert "summary.json is not JSON" in out and "holds a JSON list" in out
    assert "actor.pt is not the file its summary records (0 bytes where 7 were written)" in out
    assert "no completed run with a loadable policy" in out or "matplotlib" in out
    table = (tmp_path / "report" / "table.md").read_text()
    assert "95.0 ± 5.0 (n=2; 3 episodes)" in table and "paper 94.4 ± 3.8" in table
    assert "1 diverged" in table
    runs_csv = (tmp_path / "report" / "runs.csv").read_text().splitlines()
    assert runs_csv[0] == ("er,algo,seed,status,final_mean,episodes,code,folder,train_tracks,eval_own_track,"
                           "eval_unseen_mean,numerics,oracle,normalised")
    assert "hybrid,ppo_log,1,diverged,,3,0123456789abcdef,ppo_log/hybrid/seed1,fixed,,,portable (AVX2 kernels),," in runs_csv
    assert "recent,spg,1,completed,90.0,3,0123456789abcdef,spg/recent/seed1,fixed,,,portable (AVX2 kernels),," in runs_csv
    assert ",,,partial,,3,not recorded,spg/recent/seed3,fixed,,,not recorded,," in runs_csv
    csv_rows = (tmp_path / "report" / "table.csv").read_text().splitlines()
    assert csv_rows[0] == "er,algo,n,mean,sem,diverged,paper_mean,paper_sem,z,episodes"
    assert any(r.startswith("hybrid,ppo_log,0,,,1,,,") for r in csv_rows)


def test_oracle_normalised_scores_by_hand(tmp_path, monkeypatch, capsys):
    """0 = standing still, 1 = the oracle on the run's track; runs on tracks the oracle did not
    score are left out."""
    from analysis import report as analysis

    oracle = tmp_path / "oracle.csv"
    oracle.write_text("run,algo,track,episodes,mean_reward\noracle,oracle,1,5,160.0\noracle,oracle,2,5,200.0\n")
    monkeypatch.setattr(analysis, "ORACLE_TABLE", oracle)
    sweep = tmp_path / "sweep"
    fake_run(sweep, "spg", "recent", 1, 80.0)
    fake_run(sweep, "spg", "recent", 2, 150.0)
    fake_run(sweep, "spg", "recent", 3, 99.0)  # no oracle score for track 3
    fake_run(sweep, "sac", "memory", 2, 190.0)
    assert report.main([str(sweep), "--no-figures"]) == 0
    text = (sweep / "report" / "normalised.md").read_text()
    assert "| recent / SPG single | 2 | 0.625 ± 0.125 | 0.625 | 0.500 | 0.750 |" in text
    assert "| memory / SAC | 1 | 0.950 (n/a: one run) | 0.950 | 0.950 | 0.950 |" in text  # on 258b7c4: "± nan"
    assert "(2 tracks): 1: 160.0, 2: 200.0" in text
    runs_csv = (sweep / "report" / "runs.csv").read_text()
    assert ",160.0,0.5\n" in runs_csv and ",200.0,0.75\n" in runs_csv


def test_report_refuses_to_mix_code_versions_unless_allowed(tmp_path, capsys):
    fake_run(tmp_path, "spg", "recent", 1, 90.0)
    fake_run(tmp_path, "spg", "recent", 2, 100.0, code={**CODE, "source": "fedcba9876543210"})
    fake_run(tmp_path, "spg", "recent", 3, 95.0, code={**CODE, "resumed_from": {"source": "fedcba9876543210"}})
    fake_run(tmp_path, "spg", "memory", 1, 95.0, code=None)  # a run from before versions were recorded
    assert report.main([str(tmp_path), "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert "holds runs of 4 versions of the code" in err
    for key in ("0123456789abcdef:", "fedcba9876543210:", "0123456789abcdef resumed from fedcba9876543210:",
                "not recorded:"):
        assert key in err
    assert not (tmp_path / "report").exists()
    assert report.main([str(tmp_path), "--no-figures", "--allow-mixed-versions"]) == 0
    table = (tmp_path / "report" / "table.md").read_text()
    assert table.count("Code: ") == 4
    assert "commit aaaaaaaaaaaa (clean), source 0123456789abcdef; numerics: portable (AVX2 kernels) (1 runs)" in table


def test_report_states_the_one_version(tmp_path, capsys):
    fake_run(tmp_path, "spg", "recent", 1, 90.0)
    fake_run(tmp_path, "spg", "recent", 2, 100.0)
    assert report.main([str(tmp_path), "--no-figures"]) == 0
    first_line = (tmp_path / "report" / "table.md").read_text().splitlines()[0]
    assert first_line == ("Code: commit aaaaaaaaaaaa (clean), source 0123456789abcdef; numerics: portable (AVX2 "
                          "kernels) (2 runs)")
    assert first_line in capsys.readouterr().out


def test_report_refuses_to_mix_numerics_unless_allowed(tmp_path, capsys):
    fake_run(tmp_path, "spg", "recent", 1, 90.0)
    fake_run(tmp_path, "spg", "recent", 2, 100.0, numerics={"mode": "native", "kernels": "AVX512"})
    fake_run(tmp_path, "spg", "recent", 3, 95.0, numerics=None)  # from before the modes: native, software's cpu
    assert report.main([str(tmp_path), "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert "holds runs of 3 numerics" in err
    for key in ("portable (AVX2 kernels): 1 runs", "native (AVX512 kernels): 1 runs", "native (AVX2 kernels): 1 runs"):
        assert key in err
    assert not (tmp_path / "report").exists()
    assert report.main([str(tmp_path), "--no-figures", "--allow-mixed-numerics"]) == 0
    table = (tmp_path / "report" / "table.md").read_text()
    assert table.count("Code: ") == 3 and "numerics: native (AVX512 kernels) (1 runs)" in table


def test_report_refuses_to_mix_compiled_and_eager_runs(tmp_path, capsys):
    """Compiled update steps round differently from eager ones: like numerics, never mixed silently."""
    fake_run(tmp_path, "spg", "recent", 1, 90.0, compiled=True)
    fake_run(tmp_path, "spg", "recent", 2, 100.0, compiled=False)
    fake_run(tmp_path, "spg", "recent", 3, 95.0)  # from before compile=: eager
    assert report.main([str(tmp_path), "--no-figures"]) == 2
    err = capsys.readouterr().err
    assert "holds runs of 2 numerics" in err and "compile=" in err
    assert "portable (AVX2 kernels), compiled: 1 runs" in err and "portable (AVX2 kernels): 2 runs" in err
    assert report.main([str(tmp_path), "--no-figures", "--allow-mixed-numerics"]) == 0
    assert "numerics: portable (AVX2 kernels), compiled (1 runs)" in (tmp_path / "report" / "table.md").read_text()


def test_report_refuses_a_folder_without_runs(tmp_path, capsys):
    assert report.main([str(tmp_path)]) == 2
    assert "no runs under" in capsys.readouterr().err
    assert report.main([str(tmp_path / "missing")]) == 2
    assert "is not a folder" in capsys.readouterr().err


@pytest.mark.slow
def test_tiny_sweep_then_report_and_evaluate(tmp_path, capsys):
    """2 configurations x 2 seeds x 3 episodes, end to end: sweep, report with figures, evaluate."""
    pytest.importorskip("matplotlib", reason="the report's figures need the render extra")
    from tests.test_train import run_train

    import evaluate

    sweep = tmp_path / "sweep"
    result = run_train("-m", "algo=spg_p,ppo", "er=recent", "seed=2067791,773203", "episodes=3", "progress=false",
                       "logger=none", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert report.main([str(sweep)]) == 0
    out = sweep / "report"
    for name in ("table.md", "table.csv", "iqm.md", "iqm.png", "curves_spg_p.png", "curves_ppo.png",
                 "curves_er-recent.png", "paper_tracks.png", "agent.png"):
        assert (out / name).stat().st_size > 0, name
    table = (out / "table.md").read_text()
    assert "(n=2; 3 episodes)" in table and "paper 121.5 ± 5.8" in table
    assert table.startswith("Code: commit ") and "(4 runs)" in table
    assert "| recent / SPG-p single |" in (out / "iqm.md").read_text()
    capsys.readouterr()

    run = sweep / "spg_p" / "recent" / "seed773203"
    video = tmp_path / "agent.gif"
    assert evaluate.main([str(run), "--tracks", "2067791", "773203", "--episodes", "2", "--video", str(video)]) == 0
    printed = capsys.readouterr().out
    assert "track 2067791: mean total reward" in printed and "track 773203" in printed
    assert video.stat().st_size > 0


def test_evaluate_refuses_a_folder_that_is_not_a_run(tmp_path, capsys):
    import evaluate

    assert evaluate.main([str(tmp_path)]) == 2
    assert "no summary.json" in capsys.readouterr().err


def test_conclusions_pair_by_track_and_bootstrap_over_tracks(tmp_path):
    """Hand-made finals: PPO beats SPG by exactly 10 on every paper track (a zero-width
    interval: holds), SPG-p's spread equals SPG's (undecided), and the other tracks reverse
    the first claim; the two track sets are reported side by side."""
    from analysis.report import PAPER_SEEDS, conclusions, conclusions_markdown

    extra = [11, 12, 13, 14, 15]
    for i, seed in enumerate(PAPER_SEEDS):
        fake_run(tmp_path, "ppo", "recent", seed, 100.0 + 3 * i)
        fake_run(tmp_path, "spg", "recent", seed, 90.0 + 3 * i)
        fake_run(tmp_path, "spg_p", "recent", seed, 50.0 + 3 * i)
    for i, seed in enumerate(extra):
        fake_run(tmp_path, "ppo", "recent", seed, 100.0 + i)
        fake_run(tmp_path, "spg", "recent", seed, 130.0 + i)
    fake_run(tmp_path, "spg", "recent", 99, None, status="diverged")
    runs = find_runs(tmp_path)
    effects = {e.label: e for e in conclusions(runs, set(PAPER_SEEDS))}
    first = effects["PPO linear - SPG single (recent)"]
    assert (first.value, first.low, first.high, first.tracks, first.verdict) == (10.0, 10.0, 10.0, 5, "holds")
    spread = effects["SD(SPG single) - SD(SPG-p single) (recent)"]
    assert spread.value == pytest.approx(0.0) and spread.verdict == "undecided"
    everything = {e.label: e for e in conclusions(runs)}["PPO linear - SPG single (recent)"]
    assert everything.tracks == 10 and everything.value == pytest.approx((5 * 10 - 5 * 30) / 10)
    table = conclusions_markdown(runs)
    assert "paper tracks: effect" in table and "all 11 tracks: effect" in table
    assert "| PPO beats SPG with recent experience only | PPO linear - SPG single (recent) | +10.0 [+10.0, +10.0] (5) | holds |" in table


def test_collapse_rates_per_cell(tmp_path):
    from analysis.report import collapse_markdown

    for seed, final in zip(range(4), [120.0, 0.5, -12.0, 80.0]):
        fake_run(tmp_path, "spg", "recent", seed, final)
    fake_run(tmp_path, "spg", "recent", 9, None, status="diverged")
    text = collapse_markdown(find_runs(tmp_path))
    assert "| recent / SPG single | 4 | 2 | 50% | 1 | 1 (0.5), 2 (-12.0) |" in text
    assert "budgets" not in text  # one budget: nothing to say
    fake_run(tmp_path, "ppo", "recent", 5, 3.0, episodes=10)
    note = collapse_markdown(find_runs(tmp_path)).splitlines()[-1]
    assert note.startswith("Note: these runs were trained for different budgets (10 episodes: 1 run (recent / "
                           "PPO linear); 3 episodes: 5 runs (recent / SPG single))")


def test_iqm_is_over_runs(tmp_path):
    pytest.importorskip("matplotlib", reason="report_figures needs the render extra")
    from analysis.figures import iqm_rows

    for seed, final in zip(range(8), [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 1000.0]):
        fake_run(tmp_path, "spg", "memory", seed, final, episodes=25)
    ((label, point, low, high, n),) = iqm_rows(find_runs(tmp_path), reps=500)
    assert n == 8 and point == pytest.approx(45.0)  # the middle four of eight finals
    assert low < point < high


def test_beyond_the_paper_and_generalisation_tables_by_hand(tmp_path, capsys):
    """SAC is 10 above the paper's best cell on every paper track (a zero-width interval, verdict
    higher); a population's CPU time (or, for runs that did not record it, its wall time) is split
    over its members; random-track runs stay out of
    Table 1 and appear in the generalisation table with their own-track and unseen scores; a track
    beyond the paper's adds an all-tracks section to both tables."""
    from analysis.report import PAPER_SEEDS

    def summary(folder, track="fixed", evaluation=None, wall=50.0, size=5, cpu=None):
        data = json.loads((folder / "summary.json").read_text())
        data.update(settings={"env": {"track": track}}, wall_time_s=wall, population={"size": size})
        if cpu is not None:
            data["cpu_time_s"] = cpu
        if evaluation:
            data["evaluation"] = evaluation
        write_summary(folder, data)

    for i, seed in enumerate(PAPER_SEEDS):
        best = fake_run(tmp_path / "fixed", "spg_p_multi", "memory", seed, 120.0 + i)
        summary(best, wall=100.0, cpu=60.0)
        sac = fake_run(tmp_path / "fixed", "sac", "memory", seed, 130.0 + i)
        summary(sac, evaluation={"own_track": 140.0, "mean": 100.0 + i, "episodes": 2, "tracks": {"1": 0, "2": 0}})
        moved = fake_run(tmp_path / "random", "sac", "memory", seed, 5.0)  # random tracks: not Table 1's
        summary(moved, track="random", evaluation={"own_track": 120.0, "mean": 118.0, "episodes": 2,
                                                    "tracks": {"1": 0, "2": 0}})
    extra = fake_run(tmp_path / "fixed", "sac", "memory", 77, 136.0)  # a sixth track, fixed only
    summary(extra, evaluation={"own_track": 140.0, "mean": 108.0, "episodes": 2, "tracks": {"1": 0, "2": 0}})
    fake_run(tmp_path / "fixed", "td3", "memory", PAPER_SEEDS[0], 3.0)  # one collapsed run (final < 20)
    older = json.loads((extra / "summary.json").read_text())  # resumed, by code that kept one session's wall time
    older.update({"resumed_at": 30, "time/rollout_s": 20.0, "time/train_s": 280.0})
    write_summary(extra, older)
    assert report.main([str(tmp_path), "--no-figures"]) == 0
    beyond = (tmp_path / "report" / "beyond.md").read_text()
    assert "| SAC, memory | 5 | 132.0 ± 0.7 | 132.0 [" in beyond
    assert "| TD3, memory | 1 | 3.0 | 3.0 | -117.0 | 1 | 0 |  |" in beyond
    assert "### On all 6 tracks" in beyond and "| SAC, memory | 6 | 132.7 ± 0.9 |" in beyond
    (sac_all,) = [line for line in beyond.splitlines() if line.startswith("| SAC, memory | 6 |")]
    assert sac_all.endswith("| 0 | 0 | 0.3 min wall |")  # (5 x 10 s + 300 s / 5) / 6: the resumed run's timed phases
    assert "+10.0 [+10.0, +10.0] higher | 0 | 0 | 0.2 min wall |" in beyond
    assert "| SPG-p multiple, memory | 5 | 122.0 ± 0.7 |" in beyond and "(reference) | 0 | 0 | 0.2 min |" in beyond
    general = (tmp_path / "report" / "generalisation.md").read_text()
    assert "| SAC, memory | fixed | 5 | 140.0 ± 0.0 | 102.0 ± 0.7 (2 tracks x 2 episodes) | 38.0 ± 0.7 |" in general
    assert "| SAC, memory | random | 5 | 120.0 ± 0.0 | 118.0 ± 0.0 (2 tracks x 2 episodes) | 2.0 ± 0.0 |" in general
    paper, everything = general.split("### Trained on all 6 tracks")
    assert "| SAC, memory | fixed | 6 | 140.0 ± 0.0 | 103.0 ± 1.2 (2 tracks x 2 episodes) | 37.0 ± 1.2 |" in everything
    assert "| fixed | 6 |" not in paper and "| random |" not in everything  # random runs: paper tracks only
    table = (tmp_path / "report" / "table.md").read_text()
    assert "122.0 ± 0.7 (n=5; 3 episodes)" in table  # only the fixed-track runs of the paper's cell
    capsys.readouterr()


def test_the_frontier_curves_by_hand(tmp_path):
    """Every method against environment steps: the paper's best cell first, then the cells beyond
    the paper (SB3's too), smoothed over the last episodes; the oracle's line is its mean over the
    plotted tracks, and absent when it did not score them all; a track beyond the paper's adds a
    panel, of the cells run there; the paper's other cells stay out."""
    pytest.importorskip("matplotlib", reason="the frontier figure needs the render extra")
    from analysis.figures import frontier_figure, frontier_series
    from analysis.report import PAPER_SEEDS

    for seed in PAPER_SEEDS[:2]:
        fake_run(tmp_path, "spg_p_multi", "memory", seed, 100.0, episodes=4)  # rewards 99, 100, 101, 102
        fake_run(tmp_path, "sb3_sac", "default", seed, 110.0 + (seed == PAPER_SEEDS[1]) * 2, episodes=4)
        fake_run(tmp_path, "spg", "recent", seed, 50.0, episodes=4)
    fake_run(tmp_path, "sac", "memory", 77, 10.0, episodes=4)
    runs = find_runs(tmp_path)
    oracle = {PAPER_SEEDS[0]: 150.0, PAPER_SEEDS[1]: 160.0}
    (paper_title, paper, ceiling), (all_title, everything, no_ceiling) = frontier_series(runs, oracle, smooth=2)
    assert paper_title == "the paper's five tracks" and all_title == "all 3 tracks"
    assert [line[0] for line in paper] == ["SPG-p multiple, memory (n=2)", "Stable-Baselines3 SAC, default (n=2)"]
    label, steps, mean, sem = paper[1]
    assert list(steps) == [400, 600, 800]  # 200 steps an episode; the first point averages episodes 0 and 1
    assert list(mean) == pytest.approx([110.5, 111.5, 112.5]) and list(sem) == pytest.approx([1.0] * 3)
    assert ceiling == 155.0 and no_ceiling is None  # track 77: not scored by the oracle
    # all tracks: only the cells run beyond the paper's five (their five-track means would not compare)
    assert [line[0] for line in everything] == ["SAC, memory (n=1)"]
    assert frontier_figure(runs, oracle, tmp_path / "f.png", smooth=2).stat().st_size > 0
    assert frontier_series([r for r in runs if r.algo == "spg"], oracle) == []


def test_frontier_colours_are_one_per_cell_across_panels():
    """A cell keeps its colour in every panel (whatever its run count there), and twenty cells get
    twenty colours (matplotlib's default cycle repeats from the eleventh)."""
    from analysis.figures import cell_colours

    panels = [("five", [(f"cell {i} (n=5)",) for i in range(20)], None),
              ("all", [("cell 3 (n=25)",), ("cell 0 (n=25)",)], None)]
    colours = cell_colours(panels)
    assert list(colours) == [f"cell {i}" for i in range(20)]
    assert len(set(colours.values())) == 20


def test_the_parity_table_pairs_ours_with_theirs_by_track(tmp_path):
    """SAC at SB3's settings against SB3's SAC: the mean of the per-track differences with a
    bootstrap interval; an interval holding 0 reads "within paired noise"; a constant gap is decided."""
    from analysis.beyond import beyond_markdown
    from analysis.report import PAPER_SEEDS

    for seed, theirs, gap in zip(PAPER_SEEDS[:4], [140.0, 130.0, 150.0, 135.0], [1.0, -1.0, 3.0, 1.0]):
        fake_run(tmp_path / "a", "sb3_sac", "default", seed, theirs)
        fake_run(tmp_path / "a", "sac_sb3", "memory", seed, theirs + gap)
        fake_run(tmp_path / "b", "sb3_sac", "default", seed, theirs)
        fake_run(tmp_path / "b", "sac_sb3", "memory", seed, theirs - 5.0)
    noisy = beyond_markdown(find_runs(tmp_path / "a"))
    assert "### At equal settings" in noisy
    (row,) = [line for line in noisy.splitlines() if line.startswith("| SAC at SB3's settings, memory |")
              and "Stable-Baselines3 SAC" in line]
    assert "| 4 | +1.0 [" in row and "within paired noise" in row and "+1.0, " in row and "-1.0, " in row
    decided = beyond_markdown(find_runs(tmp_path / "b"))
    assert "| 4 | -5.0 [-5.0, -5.0] | ours lower |" in decided
    # on three tracks the interval's ends are the extreme tracks: no verdict
    shutil.rmtree(tmp_path / "b" / "sac_sb3" / "memory" / f"seed{PAPER_SEEDS[3]}")
    assert "| 3 | -5.0 [-5.0, -5.0] | too few shared tracks to decide |" in beyond_markdown(find_runs(tmp_path / "b"))
    # without the paper's best cell in the folder, no row is its reference
    assert "(no reference runs)" in noisy and "(reference)" not in noisy
    assert "At equal settings" not in beyond_markdown(find_runs(tmp_path / "a" / "sb3_sac"))


def test_the_all_tracks_section_lists_only_cells_run_beyond_the_paper_tracks(tmp_path):
    """A cell run on the paper's five tracks alone has its row there, not under "all N tracks",
    where its five-track mean would sit beside 25-track means; cells run on more tracks pair with
    the reference on their common tracks."""
    from analysis.beyond import beyond_markdown
    from analysis.report import PAPER_SEEDS

    for seed in PAPER_SEEDS:
        fake_run(tmp_path, "spg_p_multi", "memory", seed, 100.0)
        fake_run(tmp_path, "sac", "memory", seed, 110.0)
        fake_run(tmp_path, "tqc", "memory", seed, 90.0)
    for seed in (11, 12):
        fake_run(tmp_path, "spg_p_multi", "memory", seed, 100.0)
        fake_run(tmp_path, "sac", "memory", seed, 104.0)
    paper, everything = beyond_markdown(find_runs(tmp_path)).split("### On all 7 tracks")
    assert "| TQC, memory | 5 |" in paper and "TQC" not in everything
    assert "| SAC, memory | 7 |" in everything and "| SPG-p multiple, memory | 7 |" in everything
    assert "+8.3 [" in everything and "(on " not in everything  # (5 x 10 + 2 x 4) / 7, on all seven tracks
    fake_run(tmp_path, "sac", "memory", 13, 104.0)  # a track the reference was not run on
    (row,) = [line for line in beyond_markdown(find_runs(tmp_path)).split("### On all 8 tracks")[1].splitlines()
              if line.startswith("| SAC, memory |")]
    assert "| 8 |" in row and "+8.3 [" in row and "(on 7 tracks)" in row


def test_no_verdict_on_fewer_than_four_tracks(tmp_path):
    """Three tracks, each 10 higher: the bootstrap interval is [+10, +10], but its lower end is just
    the worst track (drawn three times in 1/27 of the resamples), so the table gives no verdict;
    on four tracks it does."""
    from analysis.beyond import beyond_markdown
    from analysis.report import PAPER_SEEDS

    for seed in PAPER_SEEDS:
        fake_run(tmp_path, "spg_p_multi", "memory", seed, 100.0)
    for seed in PAPER_SEEDS[:3]:
        fake_run(tmp_path, "sac", "memory", seed, 110.0)
    assert "| +10.0 [+10.0, +10.0] too few tracks to decide |" in beyond_markdown(find_runs(tmp_path))
    fake_run(tmp_path, "sac", "memory", PAPER_SEEDS[3], 110.0)
    assert "| +10.0 [+10.0, +10.0] higher |" in beyond_markdown(find_runs(tmp_path))


def test_a_copied_run_counts_once_and_is_named(tmp_path, capsys):
    """On 258b7c4 a finished run copied beside itself in a sweep (a backup) was counted again: "-18.3 ± 0.0
    (n=3)". One run is one run, however many folders hold it (engine.runset, tested hard in test_runset.py)."""
    import shutil

    original = fake_run(tmp_path, "spg", "recent", 1, 90.0)
    fake_run(tmp_path, "spg", "recent", 2, 100.0)
    backup = tmp_path / "backup" / "spg" / "recent" / "seed1"
    shutil.copytree(original, backup)
    assert report.main([str(tmp_path), "--no-figures"]) == 0
    err = capsys.readouterr().err
    assert f"report: {original} holds the same run as {backup}" in err or \
        f"report: {backup} holds the same run as {original}" in err, err
    assert (tmp_path / "report" / "runs.csv").read_text().count("seed1") == 1


def test_a_run_named_as_another_algorithm_stays_out_of_its_cell(tmp_path, capsys):
    """On 258b7c4 ``train.py algo=ppo er=recent algo.name=spg_p_multi er.name=memory`` landed a PPO result in
    SPG-p's cell: the report trusted the name over the learner the run recorded."""
    from engine.outputs import write_summary

    fake_run(tmp_path, "spg_p_multi", "memory", 1, 130.0)
    liar = fake_run(tmp_path / "elsewhere", "spg_p_multi", "memory", 2, 10.0)
    summary = json.loads((liar / "summary.json").read_text())
    summary.pop("sha256", None)
    write_summary(liar, {**summary, "settings": {"algo": {"name": "spg_p_multi", "loss": "ppo"}}})
    assert report.main([str(tmp_path), "--no-figures"]) == 0
    out = capsys.readouterr().out
    assert "conf/algo/spg_p_multi.yaml trains spg), but it recorded training ppo" in out, out
    listed = (tmp_path / "report" / "runs.csv").read_text()
    assert ",,,damaged,,3,not recorded,elsewhere/spg_p_multi/memory/seed2," in listed, listed  # not in any cell
