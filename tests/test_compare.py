"""``python -m analysis.compare``: two reports of one grid paired run by run."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from analysis.compare import compare, main, read_runs

FIELDS = ["er", "algo", "seed", "status", "final_mean"]


def write(path: Path, rows: list[tuple]) -> Path:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(FIELDS)
        writer.writerows(rows)
    return path


def test_pairs_by_cell_and_track_and_reports_what_moved(tmp_path, capsys):
    old = write(tmp_path / "old.csv", [("memory", "spg", s, "completed", v) for s, v in
                                       [(1, 100.0), (2, 110.0), (3, 120.0), (4, 10.0)]]
                + [("recent", "ppo", 1, "completed", 50.0), ("recent", "ppo", 9, "completed", 70.0)])
    new = write(tmp_path / "new.csv", [("memory", "spg", s, "completed", v) for s, v in
                                       [(1, 101.0), (2, 108.0), (3, 120.0), (4, 130.0)]]
                + [("recent", "ppo", 1, "diverged", ""), ("recent", "ppo", 9, "completed", 60.0)])
    assert main([str(new), str(old), "--markdown", str(tmp_path / "out.md")]) == 0
    text = capsys.readouterr().out
    # pairs: spg 1-4 and ppo 9 (ppo 1 did not complete in the new report)
    assert text.startswith("5 runs paired (5 new, 6 old completed runs): the new run is lower in 2, higher in 2, "
                           "equal in 1; difference median +0.0")
    assert "Collapsed (final below 20): 0 new, 1 old" in text
    assert "| spg/memory | 4 | 114.8 | 85.0 | +29.8 |" in text
    assert "| ppo/recent | 1 | 60.0 | 70.0 | -10.0 |  |" in text  # one pair: no standard error
    assert (tmp_path / "out.md").read_text() == text


def test_identical_reports_show_no_difference(tmp_path):
    rows = [("hybrid", "spg_p", s, "completed", 100.0 + s) for s in range(5)]
    text = compare(read_runs(write(tmp_path / "a.csv", rows)), read_runs(write(tmp_path / "b.csv", rows)))
    assert "equal in 5; difference median +0.0, mean +0.0 [+0.0, +0.0]" in text


def refused(capsys, words: str, call) -> None:
    """``call`` ends as a refusal does: one line naming ``words`` on stderr, exit status 2."""
    with pytest.raises(SystemExit) as ended:
        call()
    assert ended.value.code == 2 and words in capsys.readouterr().err


def test_a_file_that_is_not_a_runs_csv_is_refused_clearly(tmp_path, capsys):
    import os

    (tmp_path / "x.csv").write_text("a,b\n1,2\n")
    refused(capsys, "is not a report's runs.csv", lambda: read_runs(tmp_path / "x.csv"))
    refused(capsys, "cannot read", lambda: read_runs(tmp_path / "missing.csv"))
    os.mkfifo(tmp_path / "fifo.csv")
    refused(capsys, "FIFO", lambda: read_runs(tmp_path / "fifo.csv"))
    with pytest.raises(SystemExit, match="no run in common"):
        compare({("memory", "spg", 1): 1.0}, {("memory", "spg", 2): 1.0})


def test_two_different_cells_pair_by_track(tmp_path, capsys):
    rows = [("prioritised", "bro", s, "completed", 100.0 + s) for s in (1, 2, 3)] \
        + [("prioritised", "sac", s, "completed", 101.0 + 2 * s) for s in (1, 2, 3, 4)]
    runs = write(tmp_path / "runs.csv", rows)
    assert main([str(runs), str(runs), "--cells", "bro/prioritised", "sac/prioritised"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("New: bro/prioritised; old: sac/prioritised (the table's cell), paired by track\n"
                           "3 runs paired (3 new, 4 old completed runs): the new run is lower in 3")
    assert "| sac/prioritised | 3 | 102.0 | 105.0 | -3.0 |" in text
    refused(capsys, "no completed run of cell tqc/memory",
            lambda: main([str(runs), str(runs), "--cells", "tqc/memory", "sac/prioritised"]))
    refused(capsys, "a cell is algo/er", lambda: main([str(runs), str(runs), "--cells", "bro", "sac/prioritised"]))
