"""The output writer (engine.tool_output), the one answer to "may this tool write here": tested here, hard,
once, through the door's guard every tool's process sets (engine.processes.run_tool); each tool's test checks
only its command line's early refusal."""

from __future__ import annotations

import argparse
import os

import pytest

from door import files
from engine import rundir, tool_output
from tests.test_report import fake_run


@pytest.fixture
def guarded():
    tool_output.guard()
    try:
        yield
    finally:
        files.guard_writes(None)


def test_nothing_is_written_made_or_deleted_inside_a_run_folder(tmp_path, guarded):
    run = fake_run(tmp_path, "spg", "memory", 1, 1.0)
    before = sorted(os.listdir(run))
    for attempt in (lambda: files.write_text(run / "table.csv", "x"), lambda: files.write_text(run / "summary.json", "{}"),
                    lambda: files.folder(run / "report", run, create=True),
                    lambda: files.folder(run / "a" / "b", create=True),
                    lambda: files.remove(run / "metrics.csv"), lambda: files.remove_tree(run),
                    lambda: files.remove_tree(tmp_path / "spg"),  # a tree with a run below it
                    lambda: os.close(files.open_append(run / "metrics.csv"))):
        with pytest.raises(files.FileRefused, match=f"inside the run folder {run}|is the run folder {run}"):
            attempt()
    assert sorted(os.listdir(run)) == before
    files.write_text(tmp_path / "table.csv", "x")  # beside it: fine


def test_no_output_over_a_file_the_tool_read(tmp_path, guarded):
    table = tmp_path / "in.csv"
    table.write_text("a\n1\n")
    files.read_text(table, 100)
    os.symlink(table, tmp_path / "link.csv")
    for target in (table, tmp_path / "link.csv"):  # through a link too: by its real path
        with pytest.raises(files.FileRefused, match="is a file this command reads"):
            files.write_text(target, "b\n")
    assert table.read_text() == "a\n1\n"
    files.remove(tmp_path / "link.csv")  # deleting is not replacing


def test_a_link_before_dotdot_and_a_hard_link_are_seen_as_the_system_sees_them(tmp_path, guarded):
    """35048d1's hostile trial: ``--table <link into a run's .hydra>/../summary.json`` replaced the run's summary
    (the path was judged as text); ``--markdown <a hard link to the input>`` replaced the input's other name."""
    run = fake_run(tmp_path, "spg", "memory", 1, 1.0)
    (tmp_path / "s").mkdir()
    (run / "logs").mkdir()
    os.symlink(run / "logs", tmp_path / "s" / "V")  # as text, s/V/.. is s; to the system, the run
    before = (run / "summary.json").read_bytes()
    with pytest.raises(files.FileRefused, match=f"inside the run folder {run}"):
        files.write_text(tmp_path / "s" / "V" / ".." / "summary.json", "x")
    assert (run / "summary.json").read_bytes() == before
    table = tmp_path / "in.csv"
    table.write_text("a\n")
    os.link(table, tmp_path / "other_name.csv")
    files.read_text(table, 100)
    with pytest.raises(files.FileRefused, match="is a file this command reads"):
        files.write_text(tmp_path / "other_name.csv", "b\n")
    parser = argparse.ArgumentParser(prog="tool")
    with pytest.raises(SystemExit):
        tool_output.check_outputs(parser, reads=[table], markdown=tmp_path / "other_name.csv")


def test_a_run_this_tool_writes_may_be_written_unless_inside_another_run(tmp_path, guarded):
    """``baseline.py --out <a finished run>`` wrote a nested run inside it (35048d1)."""
    mine = tmp_path / "out" / "sb3_sac" / "default" / "seed1"
    with rundir.lock([mine]):
        files.write_text(mine / "summary.json", "{}")
        files.write_text(mine / "metrics.csv", "episode\n")  # a run now: its writer goes on writing it
        files.write_text(mine / "model.zip", "x")
    finished = fake_run(tmp_path, "spg", "memory", 1, 1.0)
    nested = finished / "sb3_sac" / "default" / "seed1"
    with pytest.raises(Exception, match=f"inside the run folder {finished}"):
        with rundir.lock([nested]):
            pass
    assert not (finished / "sb3_sac").exists()


def test_a_link_at_an_outputs_name_is_replaced_never_written_through(tmp_path, guarded):
    target = tmp_path / "elsewhere.csv"
    target.write_text("theirs")
    os.symlink(target, tmp_path / "table.csv")
    files.write_text(tmp_path / "table.csv", "ours")
    assert target.read_text() == "theirs" and not os.path.islink(tmp_path / "table.csv")


def test_the_command_line_is_checked_before_the_work_with_the_same_answer(tmp_path, capsys):
    run = fake_run(tmp_path, "spg", "memory", 1, 1.0)
    parser = argparse.ArgumentParser(prog="tool")
    for check in (lambda: tool_output.check_outputs(parser, table=run / "t.csv"),
                  lambda: tool_output.check_output_folder(parser, "--out", run / "board"),
                  lambda: tool_output.check_output_folder(parser, "--out", run)):
        with pytest.raises(SystemExit):
            check()
        assert f"the run folder {run}" in capsys.readouterr().err.splitlines()[-1]
    assert tool_output.output_problem(tmp_path / "t.csv") is None


def test_a_tool_sets_the_guard_and_its_pool_workers_too(tmp_path):
    """Every command's __main__ goes through run_tool (tests/test_signals.py); run_tool sets the guard."""
    from engine.pool import run_jobs
    from engine.processes import run_tool

    import signal

    run = fake_run(tmp_path, "spg", "memory", 1, 1.0)
    handlers = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert run_tool("tool", lambda: files.write_text(run / "x", "y") or 0) == 2
        assert files.guarded()
        with pytest.raises(files.FileRefused, match="inside the run folder"):
            run_jobs(write_in, [run / "a", run / "b"], 2)
    finally:
        files.guard_writes(None)
        for number, handler in handlers.items():
            signal.signal(number, handler)
    assert sorted(os.listdir(run)) == ["actor.pt", "critic.pt", "metrics.csv", "summary.json"]


def write_in(path) -> None:
    files.write_text(path, "x")
