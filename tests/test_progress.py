"""Progress for terminals and for files: a live bar on a terminal, short plain lines in a log."""

from __future__ import annotations

import io
import threading

import pytest

from engine.progress import Progress
from tests.test_train import run_train


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_file_gets_about_twenty_short_lines():
    stream = io.StringIO()
    progress = Progress("spg_p/hybrid/25 seeds", total=201, stream=stream)
    for episode in range(201):
        progress.update(reward=100.0 + episode, last20=90.5, diverged=None)
    progress.close()
    lines = stream.getvalue().splitlines()
    assert 20 <= len(lines) <= 22 and "\r" not in stream.getvalue()
    assert max(map(len, lines)) <= 200
    assert lines[-1].startswith("spg_p/hybrid/25 seeds: episode 201/201 (100%), reward 300.0, last20 90.5")
    assert "left" not in lines[-1] and "~" in lines[0]


def test_a_resumed_run_counts_from_where_it_resumed_and_a_slow_run_prints_by_time():
    stream = io.StringIO()
    progress = Progress("ppo/recent/seed3", total=100, initial=40, stream=stream, interval=0.0)
    progress.update(reward=1.0)
    assert stream.getvalue().startswith("ppo/recent/seed3: episode 41/100 (41%), reward 1.0")


def test_disabled_progress_prints_nothing():
    stream = Terminal()
    progress = Progress("x", total=10, enabled=False, stream=stream)
    progress.update(reward=1.0)
    progress.close()
    assert stream.getvalue() == "" and progress.bar is None


def test_a_terminal_gets_a_bar_with_a_thread_lock():
    """tqdm's default lock is a multiprocessing lock (a helper process that SLURM's signals reach);
    the bar uses a thread lock instead."""
    from tqdm import tqdm

    stream = Terminal()
    progress = Progress("x", total=10, stream=stream)
    progress.update(reward=1.5, last20=2.0)
    progress.close()
    assert "\r" in stream.getvalue() and "reward=1.5" in stream.getvalue()
    assert type(tqdm.get_lock()) is type(threading.RLock())


@pytest.mark.slow
def test_a_piped_run_writes_no_long_lines(tmp_path):
    result = run_train("algo=spg", "er=recent", "seed=3", "episodes=30", "logger=none", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("spg/recent/seed3: episode")]
    assert 15 <= len(lines) <= 17 and lines[-1].startswith("spg/recent/seed3: episode 30/30 (100%)")
    assert all(", last20 " in line for line in lines)  # the final performance's window


def test_the_progress_line_names_the_window_the_run_has(tmp_path):
    """On 258b7c4 a 10-episode run's line said ``last20``: it averages the final window, min(20, episodes)."""
    result = run_train("algo=spg", "er=recent", "seed=3", "episodes=4", "logger=none", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("spg/recent/seed3: episode")]
    assert lines and all(", last4 " in line and "last20" not in line for line in lines), lines
    assert max(len(line) for line in (result.stdout + result.stderr).splitlines()) <= 200
