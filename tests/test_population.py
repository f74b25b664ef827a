"""Populations: several runs trained in lockstep in one process, each exactly its solo run.

A solo run is a population of one, so "a member equals its solo run" is checked bit for bit
on metrics.csv (every episode's reward and every loss diagnostic), whatever the other members
and their order; divergence of one member leaves the others untouched; a killed population
resumes exactly.
"""

import json
import os
import signal
import subprocess
import sys
import time

import pytest
import torch

from engine import checkpoint
from learners.monte_carlo.learner import PhaseRunner
from engine.runner import split_members, train, train_population
from tests.test_config import load
from tests.test_resilience import interrupted_after
from tests.test_train import ENV, ROOT, read_rows, run_train

A, B, C, D = 2067791, 5468063, 773203, 5412436
CASES = [("spg_p", "hybrid"), ("ppo_log", "memory")]  # SPG and PPO, both replay phases


def common(algo, er, episodes=4):
    return [f"algo={algo}", f"er={er}", f"episodes={episodes}", "progress=false", "logger=none"]


def seeds(*values):
    return f"seeds=[{','.join(map(str, values))}]"


@pytest.mark.parametrize("algo, er", [pytest.param(*CASES[0], marks=pytest.mark.slow), CASES[1]])
def test_each_member_equals_its_solo_run_in_any_order(tmp_path, algo, er):
    train(load(*common(algo, er), f"seed={B}"), tmp_path / "solo")
    train_population(load(*common(algo, er), seeds(A, B, C)), tmp_path / "abc")
    train_population(load(*common(algo, er), seeds(C, B)), tmp_path / "cb")
    solo = (tmp_path / "solo" / "metrics.csv").read_bytes()
    assert (tmp_path / "abc" / f"seed{B}" / "metrics.csv").read_bytes() == solo
    assert (tmp_path / "cb" / f"seed{B}" / "metrics.csv").read_bytes() == solo
    assert ((tmp_path / "abc" / f"seed{C}" / "metrics.csv").read_bytes()
            == (tmp_path / "cb" / f"seed{C}" / "metrics.csv").read_bytes())
    assert solo != (tmp_path / "abc" / f"seed{A}" / "metrics.csv").read_bytes()  # members differ
    summary = json.loads((tmp_path / "abc" / f"seed{C}" / "summary.json").read_text())
    assert summary["seed"] == C and summary["status"] == "completed"
    assert summary["population"] == {"seeds": [A, B, C], "size": 3}
    for name in ("actor", "critic"):  # saved in the solo networks' layout, the same weights
        solo_weights = torch.load(tmp_path / "solo" / f"{name}.pt")
        member = torch.load(tmp_path / "cb" / f"seed{B}" / f"{name}.pt")
        assert solo_weights.keys() == member.keys()
        assert all(torch.equal(solo_weights[k], member[k]) for k in member)


def test_a_diverging_member_is_frozen_and_the_others_go_on(tmp_path, monkeypatch):
    """Member A's critic is poisoned in its third phase; B ends exactly as when trained alone."""
    run = common("spg_p", "hybrid", episodes=5)
    train(load(*run, f"seed={B}"), tmp_path / "solo")
    original, calls = PhaseRunner.run, []

    def poisoned(self, *args):
        calls.append(1)
        if len(calls) == 3:
            with torch.no_grad():
                self.optimisers.critic.params[0][0].fill_(float("inf"))
        return original(self, *args)

    monkeypatch.setattr(PhaseRunner, "run", poisoned)
    summaries = train_population(load(*run, seeds(A, B)), tmp_path / "pop")
    assert [s["status"] for s in summaries] == ["diverged", "completed"]
    assert summaries[0]["diverged"]["episode"] == 1 and "critic" in summaries[0]["diverged"]["reason"]
    assert len(read_rows(tmp_path / "pop" / f"seed{A}" / "metrics.csv")) == 1
    assert not (tmp_path / "pop" / f"seed{A}" / "actor.pt").exists()
    assert ((tmp_path / "pop" / f"seed{B}" / "metrics.csv").read_bytes()
            == (tmp_path / "solo" / "metrics.csv").read_bytes())


@pytest.mark.slow
def test_a_population_split_over_processes_killed_and_resumed_gives_its_unsplit_results(tmp_path):
    """processes=2 trains [A, B, C, D] as two populations, (A, B) and (C, D), in two processes, each with its
    own checkpoint. The parent is killed (SIGKILL, it alone) after both parts have saved one: the
    parts end with it (none writes on). Resumed with processes=1 (the parts go on as they were,
    one at a time), every member's metrics.csv is its unsplit, uninterrupted population's."""
    run = [*common("spg_p", "hybrid", episodes=10), "checkpoint_every=2", seeds(A, B, C, D)]
    reference = tmp_path / "reference"
    train_population(load(*run), reference)
    run_dir = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "train.py"), *run, f"hydra.run.dir={run_dir}"]
    parts = [run_dir / f"checkpoint-{A}.pt", run_dir / f"checkpoint-{C}.pt"]  # the same speed
    proc = subprocess.Popen([*cmd, "processes=2"], cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        # both parts have saved a checkpoint, and B has written an episode past one (a resume must drop it)
        if all(p.exists() for p in parts) and len(read_rows(run_dir / f"seed{B}" / "metrics.csv")) % 2 == 1:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the population finished before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 10  # the parts notice within a second
    while time.time() < deadline and _group_alive(proc.pid):
        time.sleep(0.1)
    assert not _group_alive(proc.pid), "a part trained on after its parent died"
    assert not (run_dir / checkpoint.CHECKPOINT_FILE).exists()
    resumed = run_train(*run, f"hydra.run.dir={run_dir}", "processes=1")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    for seed in (A, B, C, D):
        summary = json.loads((run_dir / f"seed{seed}" / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["resumed_at"] in (2, 4, 6, 8)
        assert summary["population"]["seeds"] == ([C, D] if seed in (C, D) else [A, B])
        assert ((run_dir / f"seed{seed}" / "metrics.csv").read_bytes()
                == (reference / f"seed{seed}" / "metrics.csv").read_bytes())
    assert not checkpoint.in_folder(run_dir)


def _group_alive(group: int) -> bool:
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    return True


def test_members_split_into_near_equal_parts():
    assert split_members((1, 2, 3, 4, 5), 2) == [(1, 2, 3), (4, 5)]
    assert split_members((1, 2, 3), 2, at_least=2) == [(1, 2, 3)]  # compiled: no part of one
    assert split_members((1, 2, 3, 4), 8, at_least=2) == [(1, 2), (3, 4)]
    assert split_members((1,), 4) == [(1,)] and split_members((), 2) == []


@pytest.mark.slow
def test_finished_members_are_skipped(tmp_path):
    """A member whose folder holds the same run, finished (here: trained alone), is not trained
    again; the others are."""
    run = common("ppo", "recent", episodes=2)
    solo = run_train(*run, f"seed={A}", f"hydra.run.dir={tmp_path / f'seed{A}'}")
    assert solo.returncode == 0, solo.stderr[-2000:]
    before = (tmp_path / f"seed{A}" / "summary.json").read_bytes()
    result = run_train(*run, seeds(A, B), f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-2000:]
    assert f"seed{A}: already completed" in result.stderr
    assert (tmp_path / f"seed{A}" / "summary.json").read_bytes() == before
    assert json.loads((tmp_path / f"seed{B}" / "summary.json").read_text())["population"]["size"] == 1


@pytest.mark.slow
def test_the_default_run_folders(tmp_path):
    """One run: .../<algo>/<er>/seed<seed>; a population: its members' seed<seed>/ under .../<algo>/<er>."""
    result = run_train(*common("ppo", "recent", episodes=1), seeds(A, C), "checkpoint_every=0", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    for seed in (A, C):
        assert (tmp_path / "outputs" / "runs" / "ppo" / "recent" / f"seed{seed}" / "summary.json").exists()
    result = run_train(*common("ppo", "recent", episodes=1), f"seed={B}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "outputs" / "runs" / "ppo" / "recent" / f"seed{B}" / "summary.json").exists()


@pytest.mark.slow
def test_a_population_with_a_finished_member_resumes(tmp_path):
    """Member A finished earlier (alone); B is trained, interrupted after a checkpoint, and
    resumed: B equals its uninterrupted run and A's summary is returned untouched."""
    run = [*common("ppo", "recent", episodes=4), "checkpoint_every=2"]
    train(load(*run, f"seed={A}"), tmp_path / "pop" / f"seed{A}")
    train(load(*run, f"seed={B}"), tmp_path / "alone")
    with interrupted_after(2):
        train_population(load(*run, seeds(A, B)), tmp_path / "pop")
    assert (tmp_path / "pop" / checkpoint.CHECKPOINT_FILE).exists()
    summaries = train_population(load(*run, seeds(A, B)), tmp_path / "pop")
    assert [s["seed"] for s in summaries] == [A, B] and summaries[1]["resumed_at"] == 2
    assert summaries[0]["population"]["size"] == 1
    assert ((tmp_path / "pop" / f"seed{B}" / "metrics.csv").read_bytes()
            == (tmp_path / "alone" / "metrics.csv").read_bytes())


def test_device_cpu_is_the_default_and_cuda_needs_a_gpu():
    from engine.config import ConfigError

    assert load().device == "cpu"
    with pytest.raises(ConfigError, match="device must be cpu, cuda or cuda:<index>"):
        load("device=gpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="CUDA device"):
            load("device=cuda")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU (none visible to torch)")
def test_a_population_trains_and_resumes_on_a_gpu(tmp_path):
    """Networks, losses, generators and replay memory on the GPU (the simulator on the CPU): the
    run completes, resumes exactly from a checkpoint, and its weights load on the CPU."""
    run = [*common("spg_p", "hybrid", episodes=4), "checkpoint_every=2", "device=cuda", seeds(A, B)]
    reference = train_population(load(*run), tmp_path / "reference")
    assert all(s["status"] == "completed" for s in reference)
    with interrupted_after(2):
        train_population(load(*run), tmp_path / "run")
    train_population(load(*run), tmp_path / "run")
    for seed in (A, B):
        assert ((tmp_path / "run" / f"seed{seed}" / "metrics.csv").read_bytes()
                == (tmp_path / "reference" / f"seed{seed}" / "metrics.csv").read_bytes())
        weights = torch.load(tmp_path / "run" / f"seed{seed}" / "actor.pt", weights_only=True)
        assert all(t.device.type == "cpu" for t in weights.values())


@pytest.mark.slow
def test_the_allocator_setting_changes_no_number(tmp_path):
    """keep_freed_memory (engine/processes.py) only changes where memory comes from: a population
    trained in a process that set it equals one trained in a fresh process without it."""
    from engine import processes

    code = ("import sys; from pathlib import Path; from engine import numerics; numerics.apply(numerics.DEFAULT)\n"
            "import engine.processes as p; p.keep_freed_memory = lambda: False\n"
            "from tests.test_config import load; from engine.runner import train_population\n"
            f"train_population(load(*{common('spg_p', 'hybrid', 2)!r}, {seeds(A, B)!r}), Path(sys.argv[1]))")
    result = subprocess.run([sys.executable, "-c", code, str(tmp_path / "without")], capture_output=True, text=True,
                            cwd=ROOT, env=ENV, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    train_population(load(*common("spg_p", "hybrid", 2), seeds(A, B)), tmp_path / "with")
    import platform

    if platform.libc_ver()[0] == "glibc":
        assert processes.keep_freed_memory() is True  # the setting is in effect in this process
    for seed in (A, B):
        assert ((tmp_path / "with" / f"seed{seed}" / "metrics.csv").read_bytes()
                == (tmp_path / "without" / f"seed{seed}" / "metrics.csv").read_bytes())
