"""A real single-node SLURM cluster in a temporary folder, for tests and for trying the SLURM path.

Needs Debian's ``slurm-wlm`` and ``munge`` (``apt-get install slurm-wlm munge``, about 40 s) and
root (slurmd runs jobs as their user). ``SlurmCluster(folder)`` writes a ``slurm.conf`` there
(its own ports, state and logs, no accounting), starts ``munged`` if it is not running, then
``slurmctld`` and ``slurmd``, and waits until the node is idle; ``env()`` is the environment
for ``sbatch``/``squeue`` and for a submitting ``train.py`` (``SLURM_CONF``); ``stop()`` stops
both daemons. From a shell: ``python -m tests.slurm_cluster /tmp/cluster`` starts one and
prints the ``export SLURM_CONF=...`` line; ``--stop`` stops it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

DAEMONS = ("slurmctld", "slurmd", "munged", "sbatch", "scontrol")


def missing() -> str | None:
    """Why a cluster cannot be started here, or None."""
    absent = [name for name in DAEMONS if shutil.which(name) is None and not Path(f"/usr/sbin/{name}").exists()]
    if absent:
        return f"SLURM is not installed ({', '.join(absent)} not found; apt-get install slurm-wlm munge)"
    if os.geteuid() != 0:
        return "starting slurmd needs root"
    if not Path("/etc/munge/munge.key").exists():
        return "munge has no key (/etc/munge/munge.key)"
    return None


def _binary(name: str) -> str:
    return shutil.which(name) or f"/usr/sbin/{name}"


class SlurmCluster:
    def __init__(self, folder: Path, cpus: int | None = None, port: int = 16817):
        self.folder = Path(folder).resolve()
        self.host = socket.gethostname().split(".")[0]  # slurmd knows itself by the short name
        self.cpus = cpus or os.cpu_count() or 1
        self.port = port
        self.conf = self.folder / "slurm.conf"

    def env(self) -> dict:
        return {**os.environ, "SLURM_CONF": str(self.conf)}

    def write_conf(self) -> None:
        f = self.folder
        for sub in ("state", "spool"):
            (f / sub).mkdir(parents=True, exist_ok=True)
        self.conf.write_text(f"""ClusterName=racing
SlurmctldHost={self.host}
SlurmctldPort={self.port}
SlurmdPort={self.port + 1}
AuthType=auth/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation={f}/state
SlurmdSpoolDir={f}/spool
SlurmctldPidFile={f}/slurmctld.pid
SlurmdPidFile={f}/slurmd.pid
SlurmctldLogFile={f}/slurmctld.log
SlurmdLogFile={f}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
ReturnToService=2
MinJobAge=600
KillWait=2
SchedulerParameters=defer_batch
NodeName={self.host} CPUs={self.cpus} RealMemory=16000 State=UNKNOWN
PartitionName=debug Nodes={self.host} Default=YES MaxTime=INFINITE State=UP
""")

    def start(self, timeout: float = 60.0) -> "SlurmCluster":
        reason = missing()
        if reason:
            raise RuntimeError(reason)
        self.write_conf()
        if subprocess.run(["pgrep", "-x", "munged"], capture_output=True).returncode != 0:
            Path("/run/munge").mkdir(parents=True, exist_ok=True)
            shutil.chown("/run/munge", "munge", "munge")
            subprocess.run(["sudo", "-u", "munge", _binary("munged")] if shutil.which("sudo") else
                           ["runuser", "-u", "munge", "--", _binary("munged")], check=True)
        env = self.env()
        subprocess.run([_binary("slurmctld"), "-c", "-i"], env=env, check=True)  # clean state
        subprocess.run([_binary("slurmd")], env=env, check=True)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            out = subprocess.run(["sinfo", "-h", "-o", "%t"], env=env, capture_output=True, text=True)
            if out.returncode == 0 and out.stdout.strip() in ("idle", "mix", "alloc"):
                return self
            time.sleep(0.5)
        self.stop()
        tail = ""
        for log in ("slurmctld.log", "slurmd.log"):
            path = self.folder / log
            lines = path.read_text(errors="replace").splitlines()[-2:] if path.exists() else ["(no log)"]
            tail += f" {log}: {' | '.join(lines)[:300]};"
        raise RuntimeError(f"the SLURM node did not come up in {timeout:.0f} s;{tail} (folder {self.folder})")

    def stop(self) -> None:
        for name in ("slurmd", "slurmctld"):
            pid_file = self.folder / f"{name}.pid"
            if pid_file.exists():
                try:
                    os.kill(int(pid_file.read_text().split()[0]), signal.SIGTERM)
                except (ProcessLookupError, ValueError):
                    pass
        time.sleep(1.0)

    def jobs(self) -> list[dict]:
        """Every job the controller knows (running, pending and recently ended): its id (`<array>_<task>`
        for an array task), its array's id (`job_id`), state and name."""
        out = subprocess.run(["squeue", "-h", "-t", "all", "-o", "%i|%F|%T|%j"], env=self.env(),
                             capture_output=True, text=True, check=True)
        rows = [line.split("|") for line in out.stdout.split("\n") if line.strip()]
        return [{"id": r[0], "job_id": r[1], "state": r[2], "name": r[3]} for r in rows]

    def scontrol(self, *args: str) -> str:
        return subprocess.run(["scontrol", *args], env=self.env(), capture_output=True, text=True, check=True).stdout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--stop", action="store_true")
    args = parser.parse_args()
    cluster = SlurmCluster(args.folder)
    if args.stop:
        cluster.stop()
        return
    cluster.start()
    print(f"export SLURM_CONF={cluster.conf}")


if __name__ == "__main__":
    main()
