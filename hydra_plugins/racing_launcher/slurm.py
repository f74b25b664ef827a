"""The SLURM launcher of ``hydra/launcher=slurm``: Hydra's submitit launcher, waiting differently.

Hydra's own submitit launcher submits the sweep as a job array and then waits for the jobs in
array order through submitit: the first failed job raises (a long traceback naming submitit's
``UncompletedJobError``) while the others keep running; on a cluster without accounting every
poll of ``sacct`` fails with a warning, and a job that ends without a result (cancelled,
killed, or stopped by the project's own refusal) leaves the submitting command waiting forever.

This launcher submits the same job array (same parameters, same per-job function, so requeues
on time limits and preemption work as before) and waits for every job by watching its result
file and its state in ``squeue`` (no ``sacct``). When all have ended it prints one line per job
that failed or ended without a result, with the last message of the job's own log (the
project's "Invalid configuration: ..." or "Refusing to run: ..." where there is one), and exits
with status 1: that summary is the last thing the submitting command prints.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path
from collections.abc import Sequence

from hydra.core.singleton import Singleton
from hydra.core.utils import JobReturn, filter_overrides
from hydra_plugins.hydra_submitit_launcher.config import BaseQueueConf
from hydra_plugins.hydra_submitit_launcher.submitit_launcher import SlurmLauncher as _SubmititSlurmLauncher
from omegaconf import OmegaConf

log = logging.getLogger(__name__)

ENDED = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "BOOT_FAIL", "DEADLINE",
         "SPECIAL_EXIT"}
PROJECT_MESSAGES = ("Invalid configuration:", "Refusing to run:")


class SweepJobsFailed(SystemExit):
    """Some jobs of a sweep failed; the message lists them."""


class SlurmLauncher(_SubmititSlurmLauncher):
    poll_s = 2.0  # how often the result files and squeue are read
    grace_s = 10.0  # how long an ended job may go without a result file (shared file systems lag)

    def launch(self, job_overrides: Sequence[Sequence[str]], initial_job_idx: int) -> Sequence[JobReturn]:
        import submitit

        assert self.config is not None and job_overrides
        params = dict(self.params)
        folder = params.pop("submitit_folder")
        init = {f"slurm_{key}": params.pop(key) for key in ("max_num_timeout",) if key in params}
        try:
            executor = submitit.AutoExecutor(folder=folder, cluster="slurm", **init)
        except RuntimeError as err:  # e.g. submitit's 'Could not detect "srun"': not on a SLURM cluster
            print(f"The sweep's jobs were not submitted: {_last_line(str(err))} (hydra/launcher=slurm needs a "
                  "SLURM cluster's commands: srun, sbatch, squeue)", file=sys.stderr)
            raise SweepJobsFailed(2) from None
        generic = set(OmegaConf.structured(BaseQueueConf).keys())
        executor.update_parameters(**{k if k in generic else f"slurm_{k}": v for k, v in params.items()})
        from door import files

        sweep_dir = files.folder(Path(str(self.config.hydra.sweep.dir)), create=True)
        log.info(f"Submitit 'slurm' sweep output dir : {sweep_dir}")
        arguments = []
        for idx, overrides in enumerate(job_overrides, start=initial_job_idx):
            log.info(f"\t#{idx} : {' '.join(filter_overrides(overrides))}")
            arguments.append((list(overrides), "hydra.sweep.dir", idx, f"job_id_for_{idx}", Singleton.get_state()))
        jobs = executor.map_array(self, *zip(*arguments))
        if jobs:
            log.info(f"Submitted job array {jobs[0].job_id.split('_')[0]} ({len(jobs)} jobs); waiting for all of "
                     f"them (logs in {folder.replace('%j', '<job id>')})")
        from engine.processes import STOP_FILE

        ended = wait_for(jobs, self.poll_s, self.grace_s, stop_file=sweep_dir / STOP_FILE)
        returns, failures = [], []
        for job, overrides in zip(jobs, job_overrides):
            if not ended[job.job_id]:
                failures.append((job, overrides, f"ended without a result ({job_state(job)}): " + last_message(job)))
                continue
            try:
                returns.append(job.results()[0])
            except Exception as err:  # the job's own exception, with its traceback
                failures.append((job, overrides, "failed: " + (last_message(job) or _last_line(str(err)))))
        if failures:
            lines = [f"{len(failures)} of {len(jobs)} jobs did not finish; the others' results are in their folders "
                     "(running the same command again skips them and retries these):"]
            lines += [f"  job {job.job_id} ({' '.join(filter_overrides(o))}) {why}" for job, o, why in failures]
            print("\n".join(lines), file=sys.stderr)
            raise SweepJobsFailed(1)
        return returns


SQUEUE_PATIENCE_S = 600.0  # how long squeue may keep failing before the sweep stops waiting for it


def wait_for(jobs: list, poll_s: float, grace_s: float, stop_file: Path | None = None,
             patience_s: float = SQUEUE_PATIENCE_S) -> dict[str, bool]:
    """Wait until every job has ended; {job id: whether it left a result file}. Gives up on the jobs
    still pending (False) once the sweep's stop file has been there ``grace_s`` times 6 (its jobs stop
    at their episode's end), and raises ``SweepJobsFailed`` with one line if ``squeue`` cannot be run
    at all, or fails for ``patience_s`` on end (nothing could ever say the jobs ended)."""
    from engine.processes import read_stop_file

    pending = {job.job_id: job for job in jobs}
    gone_since: dict[str, float] = {}
    outcome: dict[str, bool] = {}
    failing_since: float | None = None
    stopped_since: float | None = None
    while pending:
        states = squeue_states(sorted({j.split("_")[0] for j in pending}))
        now = time.monotonic()
        if states is None:
            failing_since = now if failing_since is None else failing_since
            if shutil.which("squeue") is None or now - failing_since > patience_s:
                print(f"Stopped waiting for the sweep's jobs: squeue {'is not installed here' if shutil.which('squeue') is None else f'has failed for {patience_s:.0f} s'}, "
                      "so nothing can tell when they end; they may still be running (the same command, run "
                      "again, skips the finished ones)", file=sys.stderr)
                raise SweepJobsFailed(1)
        else:
            failing_since = None
        if stop_file is not None and read_stop_file(stop_file) is not None:
            stopped_since = now if stopped_since is None else stopped_since
            if now - stopped_since > 6 * grace_s:
                outcome.update({job_id: job.paths.result_pickle.exists() for job_id, job in pending.items()})
                return outcome
        for job_id, job in list(pending.items()):
            if job.paths.result_pickle.exists():
                outcome[job_id] = True
            elif states is not None and states.get(job_id, "GONE") in ENDED | {"GONE"}:
                gone_since.setdefault(job_id, now)  # the result file may reach a shared file system later
                if now - gone_since[job_id] < grace_s:
                    continue
                outcome[job_id] = False
            else:
                gone_since.pop(job_id, None)
                continue
            del pending[job_id]
        if pending:
            time.sleep(poll_s)
    return outcome


def squeue_states(array_ids: list[str]) -> dict[str, str] | None:
    """{array task id: state} of these job arrays, from ``squeue`` (None if it cannot be asked)."""
    try:
        out = subprocess.run(["squeue", "-h", "-r", "-t", "all", "-j", ",".join(array_ids), "-o", "%i %T"],
                             capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0:
        return {} if "Invalid job id" in out.stderr else None  # the controller forgot them: all ended
    return dict(line.split()[:2] for line in out.stdout.splitlines() if len(line.split()) >= 2)


def job_state(job) -> str:
    states = squeue_states([job.job_id.split("_")[0]]) or {}
    return states.get(job.job_id, "no longer known to squeue")


def last_message(job) -> str:
    """The project's message from the job's stderr log, else its last line, else a pointer to it."""
    from door import files

    path = Path(job.paths.stderr)
    try:  # the log's last 64 MB at most: read bounded, as every file
        text = files.read(path, 1 << 26, "job log").decode(errors="replace")
        lines = [line.strip() for line in text.splitlines() if line.strip()]
    except (OSError, files.FileRefused) as err:
        return f"no log at {path}" if isinstance(err, FileNotFoundError) else str(err)
    for line in reversed(lines):
        if line.startswith(PROJECT_MESSAGES):
            return line
    return (_last_line("\n".join(lines)) or "empty log") + f" (log: {path})"


def _last_line(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    return lines[-1][:300] if lines else ""
