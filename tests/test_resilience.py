"""Runs that survive: kill and resume, corrupt checkpoints, divergence."""

import contextlib
import json
import signal
import subprocess
import sys
import time

import pytest
import torch

from engine import checkpoint, outputs
from engine.runner import train
from tests.test_config import load
from tests.test_train import ENV, ROOT, read_rows, run_train

RUN = ["algo=spg_p", "er=hybrid", "episodes=8", "progress=false", "logger=none", "checkpoint_every=2"]


@contextlib.contextmanager
def interrupted_after(episode: int):
    """Within the block, a run raises KeyboardInterrupt (as Ctrl-C would) right after writing
    ``episode``'s row of metrics.csv; the block expects that interruption."""
    original = outputs.MetricsWriter.write

    def write_then_stop(self, row):
        original(self, row)
        if row["episode"] == episode:
            raise KeyboardInterrupt

    outputs.MetricsWriter.write = write_then_stop
    try:
        with pytest.raises(KeyboardInterrupt):
            yield
    finally:
        outputs.MetricsWriter.write = original


def uninterrupted(tmp_path, *extra):
    out = tmp_path / "reference"
    train(load(*RUN, *extra), out)
    return (out / "metrics.csv").read_bytes()


@pytest.mark.slow
def test_sigkill_then_resume_gives_the_uninterrupted_metrics(tmp_path):
    run_dir = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "train.py"), *RUN, f"hydra.run.dir={run_dir}"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while time.time() < deadline and proc.poll() is None:
        if (run_dir / checkpoint.CHECKPOINT_FILE).exists() and len(read_rows(run_dir / "metrics.csv")) >= 5:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (run_dir / "summary.json").exists()
    resumed = run_train(*RUN, f"hydra.run.dir={run_dir}")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["resumed_at"] in (2, 4, 6)
    assert (run_dir / "metrics.csv").read_bytes() == uninterrupted(tmp_path)
    assert not (run_dir / checkpoint.CHECKPOINT_FILE).exists()


@pytest.mark.slow
@pytest.mark.parametrize("collector", ["direct", "torchrl"])
def test_resume_after_an_interruption_in_process(tmp_path, collector):
    """Stopped after episode 5 (checkpoint at 4): the resumed run equals the uninterrupted one,
    with either collector, and with the other one in the first session (summary.json's paths
    then records both)."""
    run = [*RUN, f"env.collector={collector}"]
    other = "torchrl" if collector == "direct" else "direct"
    with interrupted_after(5):
        train(load(*RUN, f"env.collector={other}"), tmp_path / "run")
    assert len(read_rows(tmp_path / "run" / "metrics.csv")) == 6
    payload = checkpoint.load(tmp_path / "run" / checkpoint.CHECKPOINT_FILE)
    assert payload["episodes_done"] == 4 and payload["loss"]["temperature"] < 1.0
    earlier_cpu = payload["timing"]["cpu_s"]  # the first session's CPU time up to its checkpoint
    summary = train(load(*run), tmp_path / "run")
    assert summary["resumed_at"] == 4 and summary["wall_time_s"] > summary["wall_time_session_s"] > 0
    assert summary["cpu_time_s"] > earlier_cpu > 0  # both sessions' CPU time
    assert (tmp_path / "run" / "metrics.csv").read_bytes() == uninterrupted(tmp_path, f"env.collector={collector}")
    assert [(path["from_episode"], path["collector"]) for path in summary["paths"]] == [(0, other), (4, collector)]


@pytest.mark.slow
def test_a_corrupt_checkpoint_is_refused_clearly(tmp_path):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / checkpoint.CHECKPOINT_FILE).write_bytes(b"\x80\x02 not a checkpoint")
    result = run_train(*RUN, f"hydra.run.dir={run_dir}")
    assert result.returncode == 2
    assert "is not a readable checkpoint" in result.stderr and "to start the run afresh" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.slow
def test_a_checkpoint_of_another_configuration_is_refused(tmp_path):
    torch.save({"version": checkpoint.VERSION, "settings": {"seed": 1}}, tmp_path / checkpoint.CHECKPOINT_FILE)
    result = run_train(*RUN, f"hydra.run.dir={tmp_path}")
    assert result.returncode == 2 and "checkpoint of a different configuration" in result.stderr


def test_checkpoints_load_with_weights_only(tmp_path):
    path = tmp_path / "c.pt"
    checkpoint.save(path, {"x": torch.ones(2), "rng": checkpoint.capture_rng()})
    assert torch.equal(checkpoint.load(path)["x"], torch.ones(2))
    assert not (tmp_path / "c.pt.tmp").exists()
    with pytest.raises(checkpoint.CheckpointError, match="no checkpoint at"):
        checkpoint.load(tmp_path / "missing.pt")


def test_divergence_stops_the_run_cleanly(tmp_path):
    """A critic learning rate of 1e30 overflows float32 within the first phase."""
    summary = train(load("algo=ppo_log", "er=recent", "episodes=4", "progress=false", "logger=none",
                         "algo.critic_lr=1e30"), tmp_path)
    assert summary["status"] == "diverged"
    assert summary["diverged"]["episode"] == 0 and "NaN or infinite" in summary["diverged"]["reason"]
    assert not (tmp_path / "actor.pt").exists()
    assert summary["episodes"] == 0 and summary["final_mean"] is None
    assert read_rows(tmp_path / "metrics.csv") == []
    stored = json.loads((tmp_path / "summary.json").read_text())
    assert stored["status"] == "diverged"


@pytest.mark.slow
def test_a_sweep_goes_on_past_a_diverged_run(tmp_path):
    result = run_train("-m", "algo=ppo_log", "er=recent", "episodes=2", "progress=false", "logger=none",
                       "algo.critic_lr=1e30,0.0005", "hydra.sweep.subdir=lr${algo.critic_lr}", "hydra/launcher=basic",
                       f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-2000:]
    statuses = {p.parent.name: json.loads(p.read_text())["status"] for p in tmp_path.glob("*/summary.json")}
    assert statuses == {"lr1e+30": "diverged", "lr0.0005": "completed"}
