"""The worker pool (engine.pool.run_jobs), the one way a tool runs jobs in processes: tested here, hard, once
(tests/test_layout.py fails a tool that starts processes itself). On 35048d1 ``analysis.planner --processes 2``
was still running a minute after SIGTERM to its pid: its pool's workers never heard it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from engine.pool import run_jobs
from engine.processes import descendants

ROOT = Path(__file__).resolve().parents[1]


def square(x: int) -> int:
    return x * x


def fail_on_two(x: int) -> int:
    if x == 2:
        raise ValueError("job 2 failed")
    return x


def wait_for_ever(folder: str) -> None:
    """A job that says it started (a file named after its process) and never ends."""
    Path(folder, str(os.getpid())).write_text("started")
    while True:
        time.sleep(1)


TOOL = """
import sys
from engine.pool import run_jobs
from engine.processes import run_tool
from tests.test_pool import wait_for_ever

def main():
    run_jobs(wait_for_ever, [sys.argv[1]] * 2, 2)
    print("a table of nothing")
    return 0

raise SystemExit(run_tool("tool", main))
"""


def test_results_in_order_in_workers_and_in_process():
    assert run_jobs(square, range(5), 2) == [0, 1, 4, 9, 16]
    assert run_jobs(square, range(5), 1) == [0, 1, 4, 9, 16]


def test_a_jobs_error_is_raised_in_the_tool_and_no_worker_is_left():
    before = set(descendants())  # the test process's own children (a zygote) are not the pool's
    with pytest.raises(ValueError, match="job 2 failed"):
        run_jobs(fail_on_two, range(4), 2)
    assert not [pid for pid in set(descendants()) - before if _alive(pid) and not _tracker(pid)]


def _tracker(pid: int) -> bool:
    """multiprocessing's resource tracker: one per process that ever started a pool, ending with it."""
    try:
        return b"resource_tracker" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def _alive(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return status != "Z"


@pytest.mark.parametrize("number", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_to_the_tool_ends_every_worker_and_no_table_is_written(tmp_path, number):
    tool = subprocess.Popen([sys.executable, "-c", TOOL, str(tmp_path)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120  # readiness: both workers have started their job (a loaded machine is slow)
    while len(list(tmp_path.iterdir())) < 2 and tool.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    workers = [int(p.name) for p in tmp_path.iterdir()]
    assert len(workers) == 2, tool.communicate()
    tool.send_signal(number)
    out, err = tool.communicate(timeout=30)
    assert tool.returncode == (143 if number == signal.SIGTERM else 130), err
    assert err.strip().splitlines()[-1] == f"tool: stopped by {signal.Signals(number).name} before it finished", err
    assert "a table" not in out
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [pid for pid in workers if _alive(pid)]
