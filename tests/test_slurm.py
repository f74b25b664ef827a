"""The SLURM path against a real SLURM: a single-node cluster started for these tests
(``tests/slurm_cluster.py``; Debian's ``slurm-wlm`` and ``munge``, root). Skipped, with the
reason, where those are not installed; ``.ci/run`` installs them when it can.

A sweep goes out as a job array through ``hydra/launcher=slurm``; a job requeued mid-run
(``scontrol requeue``: killed, queued again, started again) resumes from its checkpoint, a job
cancelled mid-run (``scancel``) is reported and resumes when the same command runs again, which
skips the finished runs; both end with the ``metrics.csv`` of an uninterrupted run. A job the
project refuses to run is reported in one line, last, with the project's message.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from tests import slurm_cluster
from tests.test_train import ENV, ROOT, run_train

REASON = slurm_cluster.missing()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"no SLURM cluster can be started here: {REASON}")

SEEDS = (11, 12)
RUN = ["algo=spg_p", "er=hybrid", f"seed={SEEDS[0]},{SEEDS[1]}", "episodes=80", "checkpoint_every=4", "logger=none"]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    folder = tmp_path_factory.mktemp("slurm")
    cluster = slurm_cluster.SlurmCluster(folder, port=16900)
    try:
        cluster.start()
    except (RuntimeError, OSError, subprocess.CalledProcessError) as err:  # installed, but no cluster here
        pytest.skip(f"SLURM is installed but a cluster could not be started here: {err}")
    yield cluster
    cluster.stop()


def slurm_sweep(cluster, *args: str, wait: bool = True):
    command = [sys.executable, str(ROOT / "train.py"), "-m", "hydra/launcher=slurm", *args]
    env = {**ENV, "SLURM_CONF": str(cluster.conf)}
    if wait:
        return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    return subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _state(cluster, job_id: str) -> str | None:
    return next((j["state"] for j in cluster.jobs() if j["id"] == job_id), None)


def rows(path) -> int:
    return max(0, len(path.read_text().splitlines()) - 1) if path.exists() else 0


@pytest.mark.slow
def test_requeued_and_cancelled_jobs_resume_exactly_and_finished_runs_are_skipped(cluster, tmp_path):
    """Job 0 is requeued mid-run (killed, queued and started again: it resumes by itself); job 1
    is cancelled mid-run (reported; the same command again resumes it and skips job 0's
    finished run). Both end with the metrics.csv of the same runs made here, uninterrupted."""
    # the reference: both runs as one population in this process (a member equals its solo run)
    local = run_train(*[a for a in RUN if not a.startswith("seed=")], f"seeds=[{SEEDS[0]},{SEEDS[1]}]",
                      f"hydra.run.dir={tmp_path / 'local'}", "progress=false")
    assert local.returncode == 0, local.stderr[-3000:]

    sweep = tmp_path / "slurm"
    folders = {seed: sweep / "spg_p" / "hybrid" / f"seed{seed}" for seed in SEEDS}
    submitting = slurm_sweep(cluster, *RUN, f"hydra.sweep.dir={sweep}", wait=False)
    deadline = time.monotonic() + 300
    while (min(rows(f / "metrics.csv") for f in folders.values()) < 9 and time.monotonic() < deadline
           and submitting.poll() is None):
        time.sleep(0.2)
    assert min(rows(f / "metrics.csv") for f in folders.values()) >= 9, "the jobs did not get going"
    newest = max(int(j["job_id"]) for j in cluster.jobs())
    jobs = {j["id"].split("_")[-1]: j for j in cluster.jobs() if j["id"].split("_")[0] == str(newest)}
    assert jobs["0"]["state"] == jobs["1"]["state"] == "RUNNING"
    cluster.scontrol("requeue", jobs["0"]["id"])  # killed (after KillWait), queued and started again
    subprocess.run(["scancel", jobs["1"]["id"]], env=cluster.env(), check=True)
    # SLURM holds a requeued job for a while (its BeginTime); release it as soon as it is pending again
    deadline, pending, restarted = time.monotonic() + 150, False, False
    while time.monotonic() < deadline and not restarted:
        state = _state(cluster, jobs["0"]["id"])
        if state == "PENDING":
            pending = True
            subprocess.run(["scontrol", "update", f"JobId={jobs['0']['id']}", "StartTime=now"], env=cluster.env(),
                           capture_output=True)
        restarted = pending and state in ("RUNNING", "COMPLETING", "COMPLETED")
        time.sleep(0.3)
    assert restarted, f"the requeued job did not start again ({state})"
    out, err = submitting.communicate(timeout=600)
    assert "Submitted job array" in out + err and "Traceback" not in err and "resource_tracker" not in err
    assert "sacct" not in out + err  # no accounting here: the launcher does not ask it
    assert submitting.returncode == 1
    assert err.strip().splitlines()[-1].startswith(f"  job {jobs['1']['id']} (") and "(CANCELLED)" in err
    first = json.loads((folders[SEEDS[0]] / "summary.json").read_text())
    assert first["status"] == "completed" and first["resumed_at"] in range(8, 80, 4)  # requeued, resumed
    assert not (folders[SEEDS[1]] / "summary.json").exists()
    log = next((sweep / ".submitit").glob(f"{jobs['0']['id']}/*_log.err")).read_text()
    assert max(len(line) for line in log.splitlines()) <= 200  # plain progress lines in a file

    stamp = (folders[SEEDS[0]] / "summary.json").stat().st_mtime_ns
    again = slurm_sweep(cluster, *RUN, f"hydra.sweep.dir={sweep}")
    assert again.returncode == 0, again.stderr[-3000:]
    assert (folders[SEEDS[0]] / "summary.json").stat().st_mtime_ns == stamp  # skipped: already completed
    second = json.loads((folders[SEEDS[1]] / "summary.json").read_text())
    assert second["status"] == "completed" and second["resumed_at"] in range(8, 80, 4)  # resumed after scancel
    for seed in SEEDS:
        assert ((sweep / "spg_p" / "hybrid" / f"seed{seed}" / "metrics.csv").read_bytes()
                == (tmp_path / "local" / f"seed{seed}" / "metrics.csv").read_bytes())


@pytest.mark.slow
def test_a_refused_job_is_reported_last_in_one_line(cluster, tmp_path):
    """A bad value is refused before anything is submitted (the sweeper checks every job); a job
    that refuses its folder at run time (a checkpoint of another run) is reported at the end."""
    import torch

    from engine import checkpoint

    bad = slurm_sweep(cluster, "algo=spg", "er=recent", "seed=11,-1", "episodes=2", "logger=none",
                      f"hydra.sweep.dir={tmp_path}")
    assert bad.returncode == 2 and "The sweep was not started: 1 of its 2 jobs" in bad.stderr
    assert "Submitted job array" not in bad.stdout + bad.stderr
    (tmp_path / "spg" / "recent" / "seed12").mkdir(parents=True)
    torch.save({"version": checkpoint.VERSION, "settings": {"seed": 12}, "members": [12]},
               tmp_path / "spg" / "recent" / "seed12" / checkpoint.CHECKPOINT_FILE)
    result = slurm_sweep(cluster, "algo=spg", "er=recent", "seed=11,12", "episodes=2", "logger=none",
                         f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 1
    last = result.stderr.strip().splitlines()[-2:]
    assert last[0].startswith("1 of 2 jobs did not finish")
    assert "seed=12" in last[1] and "Refusing to run: the run folder holds a checkpoint of a different" in last[1]
    assert "Traceback" not in result.stderr
    assert json.loads((tmp_path / "spg" / "recent" / "seed11" / "summary.json").read_text())["status"] == "completed"
