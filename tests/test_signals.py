"""Signals stop split populations and sweeps as they stop a run (issue 50; docs/guarantees.md): SIGTERM
or SIGINT sent to the parent alone, as schedulers and ``timeout`` send it, stops every member and job at
its episode's end with a checkpoint, starts no new job, leaves no process behind, and ends in one line
with exit status 130 or 143; a signal before training starts is one line too."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from engine import rundir
from engine.processes import descendants
from tests.test_run_folders import TINY, _sigint_as_in_a_terminal
from tests.test_train import ENV, ROOT

LONG = [*TINY, "episodes=100000", "checkpoint_every=50"]  # far longer than a test: it ends by the signal


def _start(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(ROOT / "train.py"), *args], cwd=ROOT, env=ENV, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=_sigint_as_in_a_terminal)


def _wait_for(paths: list[Path], proc: subprocess.Popen, seconds: float = 180) -> None:
    deadline = time.time() + seconds
    while not all(p.exists() and p.stat().st_size > 200 for p in paths):  # a header and some rows
        assert proc.poll() is None and time.time() < deadline, proc.communicate()[1][-2000:]
        time.sleep(0.1)


def _lines(err: str) -> list[str]:
    return [line for line in err.splitlines()
            if line.strip() and not line.startswith(("Note:", "[")) and "HYDRA" not in line]


def _ended_with_nothing_left(proc: subprocess.Popen, status: int, seconds: float = 120) -> str:
    children = descendants(proc.pid)
    _, err = proc.communicate(timeout=seconds)
    assert proc.returncode == status, err[-3000:]
    time.sleep(0.5)
    alive = [pid for pid in children if Path(f"/proc/{pid}").exists()
             and "Z" not in Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]]
    assert not alive, f"processes left behind: {alive}"
    return err


def _rows(folder: Path) -> int:
    return len((folder / "metrics.csv").read_text().splitlines()) - 1


@pytest.mark.slow
def test_sigterm_to_the_parent_of_a_split_population_stops_every_part_with_its_checkpoint(tmp_path):
    """A population split over processes ignored SIGTERM sent to its parent: 60 s later it still trained."""
    folder = tmp_path / "run"
    proc = _start(*LONG, "seeds=[1,2]", "processes=2", f"hydra.run.dir={folder}")
    _wait_for([folder / "seed1" / "metrics.csv", folder / "seed2" / "metrics.csv"], proc)
    proc.send_signal(signal.SIGTERM)  # the parent alone
    err = _ended_with_nothing_left(proc, 143)
    (line,) = _lines(err)
    assert line.startswith("Stopped by SIGTERM; saved checkpoint-1.pt at episode ") and \
        line.endswith(f"in {folder}: the same command resumes from there"), line
    for seed in (1, 2):
        episode = int(line.split(f"checkpoint-{seed}.pt at episode ")[1].split(",")[0].split()[0])
        assert _rows(folder / f"seed{seed}") == episode  # every row the checkpoint counts, no more
        assert rundir.state(folder / f"seed{seed}").kind == "empty"  # rows only: its part's checkpoint holds it
    assert sorted(p.name for p in rundir.checkpoints(folder)) == ["checkpoint-1.pt", "checkpoint-2.pt"]


@pytest.mark.slow
def test_sigterm_to_one_part_stops_the_whole_population(tmp_path):
    """SIGTERM sent to a worker directly did not stop the population either."""
    folder = tmp_path / "run"
    proc = _start(*LONG, "seeds=[1,2]", "processes=2", f"hydra.run.dir={folder}")
    _wait_for([folder / "seed1" / "metrics.csv", folder / "seed2" / "metrics.csv"], proc)
    workers = [pid for pid in descendants(proc.pid) if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text()]
    assert len(workers) == 2, workers
    os.kill(workers[-1], signal.SIGTERM)
    err = _ended_with_nothing_left(proc, 143)
    (line,) = _lines(err)
    assert line.startswith("Stopped by SIGTERM; saved checkpoint-") and "checkpoint-1.pt" in line \
        and "checkpoint-2.pt" in line, line


@pytest.mark.slow
def test_sigterm_to_a_sweep_stops_its_jobs_starts_no_other_and_leaves_no_process(tmp_path):
    """SIGTERM to a sweep's main process left its joblib workers running, orphaned; SIGINT stopped the
    current job only, and the sweep started the next."""
    sweep = tmp_path / "sweep"
    seeds = "1,2,3,4"
    proc = _start("-m", *LONG, f"seed={seeds}", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}")
    started = [sweep / "spg" / "recent" / f"seed{s}" / "metrics.csv" for s in (1, 2)]
    _wait_for(started, proc)
    proc.send_signal(signal.SIGTERM)  # the sweep's main process alone
    err = _ended_with_nothing_left(proc, 143)
    lines = _lines(err)
    assert lines[-1] == ("Sweep stopped by SIGTERM: 0 of 4 jobs finished, 2 stopped with a checkpoint, 2 not started "
                         "or not saved: the same command resumes it"), err[-3000:]
    assert all(line.startswith("Stopped by SIGTERM after episode ") for line in lines[:-1]) and len(lines) == 3
    for seed in (1, 2):
        assert rundir.state(sweep / "spg" / "recent" / f"seed{seed}").kind == "resumable"
    for seed in (3, 4):  # never started: nothing written
        assert not (sweep / "spg" / "recent" / f"seed{seed}" / "metrics.csv").exists()
    assert not (sweep / ".stop").exists()


def handlers_installed(pid: int, timeout: float = 120.0) -> None:
    """Wait until process ``pid`` catches SIGTERM (its ``SigCgt`` mask in /proc): train.py installs its early
    handlers for SIGINT and SIGTERM together, as its first act, so from then on a signal is its to answer.
    (A signal before that lands in the interpreter's own start-up, which no program can answer.)"""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            status = Path(f"/proc/{pid}/status").read_text()
        except FileNotFoundError:
            return  # it has ended: the caller reads how
        caught = int(next(line.split()[1] for line in status.splitlines() if line.startswith("SigCgt:")), 16)
        if caught >> (signal.SIGTERM - 1) & 1:
            return
        time.sleep(0.01)
    raise AssertionError(f"process {pid} installed no SIGTERM handler in {timeout} s")


@pytest.mark.slow
def test_a_signal_before_training_starts_is_one_line(tmp_path):
    """SIGINT in a run's first seconds gave a 78-line KeyboardInterrupt traceback. Sent as soon as the
    run answers signals (a readiness signal, not a fixed delay: under load a fixed 0.3 s once landed before
    the handler), and a second later."""
    for delay, name, status in ((0.0, "SIGINT", 130), (1.0, "SIGTERM", 143)):
        proc = _start(*TINY, f"hydra.run.dir={tmp_path / name}")
        handlers_installed(proc.pid)
        time.sleep(delay)
        proc.send_signal(getattr(signal, name))
        _, err = proc.communicate(timeout=120)
        if proc.returncode == 0:  # a machine fast enough to finish first: nothing to see
            continue
        assert proc.returncode == status, err[-3000:]
        (line,) = _lines(err)
        assert line.startswith(f"Stopped by {name} "), line


@pytest.mark.slow
def test_a_scoring_tool_stopped_by_a_signal_says_so_in_one_line(tmp_path):
    """score.py (as evaluate.py, tracks.py, drive.py: engine.processes.run_tool) on SIGTERM or SIGINT:
    one line, status 143 or 130, no traceback, no table."""
    from racing.track_file import make_circuit, write_rows

    circuit = write_rows(tmp_path / "c.csv", make_circuit(1200))
    for number, status in ((signal.SIGTERM, 143), (signal.SIGINT, 130)):
        process = subprocess.Popen([sys.executable, "score.py", "oracle", "--laps-on", str(circuit), "--table",
                                    str(tmp_path / "laps.csv")], cwd=ROOT, stdout=subprocess.PIPE,
                                   stderr=subprocess.PIPE, text=True, preexec_fn=_sigint_as_in_a_terminal)
        time.sleep(4)  # scoring the oracle on a 1,200-point circuit for three laps takes minutes
        process.send_signal(number)
        _, err = process.communicate(timeout=60)
        assert process.returncode == status, err
        assert err == f"score: stopped by {signal.Signals(number).name} before it finished\n"
        assert not (tmp_path / "laps.csv").exists()


def test_every_tool_stops_on_a_signal_in_one_line():
    """Every command-line tool but train.py (its own handling: checkpoints, sweeps) runs its main()
    through engine.processes.run_tool, which the test above drives with real signals."""
    import ast

    for tool in ("score", "evaluate", "tracks", "drive", "report", "imitate", "baseline"):
        tree = ast.parse((ROOT / f"{tool}.py").read_text())
        (block,) = [node for node in tree.body if isinstance(node, ast.If) and "__main__" in ast.unparse(node.test)]
        assert f'run_tool({tool!r}, main)' in ast.unparse(block).replace('"', "'"), tool


def test_a_signal_inside_torchs_python_code_waits_until_it_can_stop_the_tool(tmp_path):
    """An exception raised in Python code that torch's C++ runs as a callback (while torch imports,
    say) aborted the process ('terminate called after throwing pybind11::error_already_set', status
    -6) instead of one line: such a signal is sent again until it lands outside torch's code."""
    from engine.processes import deferred

    class Code:
        def __init__(self, filename):
            self.co_filename, self.co_name = filename, "f"

    class Frame:
        def __init__(self, filename, back=None, module=None):
            self.f_code, self.f_back = Code(filename), back
            self.f_globals = {"__name__": module or Path(filename).stem}

    ours = Frame("/x/racing/oracle.py", Frame("/x/score.py", module="__main__"), module="racing.oracle")
    assert not deferred(signal.SIGUSR1, ours)
    received = []
    previous = signal.signal(signal.SIGUSR1, lambda number, frame: received.append(number))
    try:
        inside = Frame("/venv/lib/python3.11/site-packages/torch/_ops.py", ours)
        assert deferred(signal.SIGUSR1, inside)
        deadline = time.monotonic() + 60
        while not received and time.monotonic() < deadline:  # sent again, 50 ms later
            time.sleep(0.01)
        assert received == [signal.SIGUSR1]
        importing = Frame("/x/racing/sim.py", Frame("/venv/lib/python3.11/site-packages/torch/__init__.py", ours,
                                                    module="torch"), module="racing.sim")
        importing.f_back.f_code.co_name = "<module>"
        assert deferred(signal.SIGUSR1, importing)  # torch's module body runs: its C++ may call back
        deadline = time.monotonic() + 60
        while len(received) < 2 and time.monotonic() < deadline:  # its re-sent signal lands here, not after
            time.sleep(0.01)
        assert received == [signal.SIGUSR1] * 2
    finally:
        signal.signal(signal.SIGUSR1, previous)
    # A planner evaluated under @torch.no_grad(): torch's wrapper is on the stack all the while (a SIGINT
    # waited for the whole evaluation and was lost when it ended); the project's code inside it stops.
    wrapper = Frame("/venv/lib/python3.11/site-packages/torch/utils/_contextlib.py", ours, module="torch.utils")
    planner = Frame("/x/learners/latent.py", Frame("/venv/lib/python3.11/site-packages/torch/nn/modules/module.py",
                                                   wrapper, module="torch.nn.modules.module"), module="learners.latent")
    assert not deferred(signal.SIGUSR2, planner)


def test_a_signal_inside_a_librarys_code_waits_a_moment_for_the_projects(monkeypatch):
    """A SIGINT landing while omegaconf set a value (Hydra composing a run's configuration) ended
    in an unrelated AttributeError from omegaconf's clean-up, a traceback instead of one line (found
    by the fault suite): a stop waits while a library's code runs, for at most a second (joblib
    waiting for its workers must not make Ctrl-C wait forever); the standard library decides nothing,
    and the project's packages are the project's wherever they are installed."""
    import tomllib

    from engine import processes

    class Code:
        def __init__(self, filename):
            self.co_filename, self.co_name = filename, "f"

    class Frame:
        def __init__(self, filename, module, back=None):
            self.f_code, self.f_globals, self.f_back = Code(filename), {"__name__": module}, back

    monkeypatch.setattr(processes.threading, "Timer", lambda *args: type("T", (), {"start": lambda self: None})())
    site = "/venv/lib/python3.11/site-packages"
    script = Frame("/x/train.py", "__main__")
    omegaconf = Frame(f"{site}/omegaconf/listconfig.py", "omegaconf.listconfig", script)
    exiting = Frame("/usr/lib/python3.11/contextlib.py", "contextlib", omegaconf)
    assert processes.deferred(signal.SIGUSR1, exiting)  # contextlib's __exit__ for omegaconf: omegaconf's
    assert not processes.deferred(signal.SIGUSR2, Frame("/usr/lib/python3.11/contextlib.py", "contextlib", script))
    installed = Frame(f"{site}/engine/config.py", "engine.config", omegaconf)
    assert not processes.deferred(signal.SIGUSR2, installed)  # the project installed beside its libraries
    clock = [100.0]
    monkeypatch.setattr(processes.time, "monotonic", lambda: clock[0])
    assert processes.deferred(signal.SIGHUP, omegaconf)
    clock[0] += 0.9
    assert processes.deferred(signal.SIGHUP, omegaconf)
    clock[0] += 0.2
    assert not processes.deferred(signal.SIGHUP, omegaconf)  # a second has passed: it stops here
    assert processes.deferred(signal.SIGHUP, omegaconf)  # a new signal waits again
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    assert {name.rstrip("*").split(".")[0] for name in declared["include"]} == set(processes.PROJECT_PACKAGES)

