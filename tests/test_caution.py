"""The decisive experiment's reading (``python -m analysis.caution``): its numbers are the runs' own evaluations
on the oracle's scale, its verdict the rule docs/results/caution/README.md wrote before the runs, and a run it
cannot read is refused in one line."""

import csv
import math

from analysis import caution
from analysis.report import read_oracles
from tests.test_offpolicy import A
from tests.test_readme import readme_commands
from tests.test_start import TINY, rows, train


def test_the_verdict_is_the_written_rule():
    assert caution.reading([-0.010, -0.02, -0.5]) == "prefers caution"
    assert caution.reading([-0.009, -0.02, -0.5]) == "mixed"
    assert caution.reading([0.0, -0.004, -0.010]) == "holds"  # mean -0.0047, none below -0.010
    assert caution.reading([0.0, 0.0, -0.011]) == "mixed"
    assert caution.reading([0.02, -0.02, -0.02]) == "mixed"  # mean -0.0067


def test_a_configuration_s_drift_has_its_t_interval_over_tracks():
    rows = [{"configuration": "c", "s0": 1.0, "lowest": 0.9, "s_end": 0.9 + d, "drift": d - 0.1, "training": 0.9}
            for d in (0.0, 0.01, 0.05)]
    [row] = caution.summary_rows(rows)
    drifts = [-0.1, -0.09, -0.05]
    sd = math.sqrt(sum((x - sum(drifts) / 3) ** 2 for x in drifts) / 2)
    assert math.isclose(row["drift"], sum(drifts) / 3) and math.isclose(row["drift_high"] - row["drift"], 4.303 * sd / math.sqrt(3))
    assert row["reading"] == "prefers caution"


def test_a_started_run_is_read_on_the_oracle_s_scale_and_one_without_evaluations_is_refused(tmp_path, capsys):
    start = tmp_path / "start"
    train(start, "algo=sac", *TINY, "episodes=2", f"seed={A}")
    sweep = tmp_path / "sweep" / "sac" / "memory"
    train(sweep / f"seed{A}", "algo=sac", *TINY, "episodes=7", f"seed={A}", f"algo.td.start_from={start}",
          "algo.td.critic_first_episodes=1", "eval_every=1", "eval_episodes=1")
    scores = [float(r["deterministic"]) for r in rows(sweep / f"seed{A}")]
    oracle = read_oracles()[A]
    [row] = caution.run_rows([sweep / f"seed{A}"], read_oracles(), last=5)
    assert row["configuration"] == "sweep/sac/memory" and row["evaluations"] == 7
    assert row["s0"] == scores[0] / oracle and row["lowest"] == min(scores[1:]) / oracle
    assert math.isclose(row["s_end"], math.fsum(scores[2:]) / 5 / oracle)
    assert math.isclose(row["drift"], row["s_end"] - row["s0"])
    for args in readme_commands("-m analysis.caution") or [["outputs/sweeps/caution"]]:
        args = [str(tmp_path / "sweep") if a.startswith("outputs/") else a for a in args]
        assert caution.main([*args, "--table", str(tmp_path / "c.csv")]) == 0
    printed = capsys.readouterr().out
    assert "| sweep/sac/memory | 1 |" in printed
    assert list(csv.DictReader((tmp_path / "c.csv").read_text().splitlines()))[0]["track"] == str(A)
    assert caution.main([str(start)]) == 2
    assert "did not start from another policy" in capsys.readouterr().err
    unscored = tmp_path / "unscored"
    train(unscored, "algo=sac", *TINY, "episodes=2", f"seed={A}", f"algo.td.start_from={start}")
    assert caution.main([str(unscored)]) == 2
    assert "train with eval_every" in capsys.readouterr().err
    assert caution.main([str(sweep / f"seed{A}"), str(sweep / f"seed{A}")]) == 0  # named twice: read once (engine.runset)
