"""The run-set reader (engine.runset), the one answer to "which runs does this command name": tested here,
hard, once; each tool's own test checks only that it asks (tests/test_layout.py fails a tool that walks
folders itself)."""

from __future__ import annotations

import os
import shutil

import pytest

from door import files
from engine.outputs import RunFolderError
from engine.runset import identity, read_runs
from tests.test_report import fake_run


def test_a_sweep_is_read_at_any_depth_in_order(tmp_path):
    runs = [fake_run(tmp_path, "spg", er, seed, 1.0) for er in ("memory", "recent") for seed in (2, 1)]
    assert read_runs([tmp_path]).runs == sorted(runs)
    assert read_runs([runs[0]]).runs == [runs[0]]  # a run names itself


def test_a_link_a_repeat_and_a_copy_count_once_each_said_in_one_line(tmp_path, capsys):
    original = fake_run(tmp_path / "sweep", "spg", "memory", 1, 90.0)
    other = fake_run(tmp_path / "sweep", "spg", "memory", 2, 91.0)
    os.symlink(original, tmp_path / "link")
    copy = tmp_path / "backup"
    shutil.copytree(original, copy)
    found = read_runs([tmp_path / "sweep", tmp_path / "link", original, copy], say="tool")
    assert found.runs == [original, other]
    err = capsys.readouterr().err.splitlines()
    assert err == [f"tool: {tmp_path / 'link'} is {original} (a link, or named twice): counted once",
                   f"tool: {copy} holds the same run as {original} (the same recorded algorithm, replay mode, seed "
                   "and settings: a copy, or the run made twice): counted once"]


def test_copies_are_told_apart_by_path_only_when_asked(tmp_path):
    original = fake_run(tmp_path, "spg", "memory", 1, 90.0)
    shutil.copytree(original, tmp_path / "copy")
    assert len(read_runs([original, tmp_path / "copy"], copies=False).runs) == 2


def test_unfinished_runs_and_a_tools_own_folder(tmp_path):
    fake_run(tmp_path, "spg", "memory", 1, summary=False)  # metrics.csv only: killed or running
    finished = fake_run(tmp_path, "spg", "memory", 2, 1.0)
    fake_run(tmp_path / "report", "spg", "memory", 3, 1.0)
    assert read_runs([tmp_path], skip_named="report").runs == [finished]
    assert len(read_runs([tmp_path], unfinished=True, skip_named="report").runs) == 2
    assert identity(tmp_path / "spg" / "memory" / "seed1") is None  # no summary: only ever itself


def test_a_chain_of_folders_deeper_than_pythons_recursion_limit(tmp_path):
    """A 1,500-deep chain of empty folders ended report.py, evaluate.py, the leaderboard and train.py in a
    RecursionError (os.walk of Python 3.11 recurses): the door's walk does not."""
    here = tmp_path
    for _ in range(1500):
        here = here / "d"
        here.mkdir()  # os.makedirs recurses too
    with pytest.raises(RunFolderError, match="holds no finished train.py run"):
        read_runs([tmp_path])
    run = fake_run(here, "spg", "memory", 1, 1.0)
    assert read_runs([tmp_path]).runs == [run]
    files.remove_tree(tmp_path / "d")  # the door's other walks too


@pytest.mark.skipif(os.geteuid() == 0, reason="root lists every folder whatever its permissions")
def test_a_folder_that_cannot_be_listed_is_skipped_in_one_line(tmp_path, capsys):
    run = fake_run(tmp_path, "spg", "memory", 1, 1.0)
    closed = tmp_path / "closed"
    closed.mkdir()
    closed.chmod(0)
    try:
        assert read_runs([tmp_path], say="tool").runs == [run]
    finally:
        closed.chmod(0o755)
    assert capsys.readouterr().err.startswith(f"tool: skipped {closed}: it cannot be listed")


def test_what_is_not_a_run_set_is_one_line(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(RunFolderError, match="is not a folder"):
        read_runs([tmp_path / "file"])
    with pytest.raises(RunFolderError, match="holds no finished train.py run"):
        read_runs([tmp_path])


def test_the_walk_matches_os_walk_top_down_and_bottom_up(tmp_path):
    for name in ("a/b/c", "a/d", "e"):
        (tmp_path / name).mkdir(parents=True)
        (tmp_path / name / "f").write_text("x")
    os.symlink(tmp_path / "a", tmp_path / "link")  # a link to a folder: listed as a name, never entered
    for topdown in (True, False):
        ours = [(h, f, n) for h, f, n in files.walk(tmp_path, topdown=topdown)]
        theirs = [(h, sorted(set(f) - {"link"}), sorted(n + ["link"] * ("link" in f)))
                  for h, f, n in os.walk(tmp_path, topdown=topdown)]
        assert sorted(ours) == sorted(theirs)
    order = [h for h, _, _ in files.walk(tmp_path, topdown=False)]
    assert order.index(str(tmp_path / "a" / "b" / "c")) < order.index(str(tmp_path / "a"))
