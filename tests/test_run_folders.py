"""Run folders that never lose or misreport a result (engine/rundir.py; docs/guarantees.md):
kills at any moment, damaged files, overwrite, two processes on one folder, full disks, sweeps
checked whole before they start, and the one-line endings of train.py."""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from engine import rundir
from engine.checkpoint import CHECKPOINT_FILE
from tests.test_train import ENV, ROOT, run_train

# A short run (episodes of 50 steps, replay memory and recent experience) checkpointed every second episode.
FAULT_RUN = ["algo=spg", "er=hybrid", "episodes=120", "checkpoint_every=2", "env.options.max_steps=50",
             "algo.minibatch_size=50", "final_window=10", "progress=false", "logger=none"]
SIGNALS = ("SIGKILL", "SIGTERM", "SIGINT")


def _sigint_as_in_a_terminal() -> None:
    """The child's SIGINT at its default, as a command typed in a terminal has it: a test run from a
    background job of a non-interactive shell inherits SIGINT ignored, and a run leaves an ignored
    SIGINT alone (engine.processes.StopSignals), so the tests' own SIGINTs would do nothing."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


class FaultServer:
    """tests/fault_server.py: forks training sessions with faults injected."""

    def __init__(self, log: Path, overrides: list[str] = FAULT_RUN):
        self.log, self.overrides = log, overrides
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.fault_server"], cwd=ROOT, env=ENV, text=True,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     preexec_fn=_sigint_as_in_a_terminal)

    def session(self, folder: Path, fault: dict | None = None, kill_after: tuple[float, str] | None = None) -> int:
        command = {"folder": str(folder), "overrides": self.overrides, "fault": fault, "log": str(self.log)}
        self.proc.stdin.write(json.dumps(command) + "\n")
        self.proc.stdin.flush()
        pid = json.loads(self.proc.stdout.readline())["pid"]
        if kill_after is not None:
            delay, name = kill_after
            time.sleep(delay)
            try:
                os.kill(pid, getattr(signal, name))
            except ProcessLookupError:
                pass
        return json.loads(self.proc.stdout.readline())["status"]

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=60)
        self.proc.stdout.close()


def fault_plan(rng: random.Random) -> tuple[list[dict], list[dict]]:
    """Faults during training (every session meets them), then faults of the final writes."""
    during = []
    for i in range(21):
        name = SIGNALS[i % 3]
        kind = i % 7
        if kind in (0, 1):
            during.append({"fault": {"at": "rename", "file": CHECKPOINT_FILE, "nth": rng.randint(1, 2),
                                     "signal": name, "torn": kind == 0}})
        elif kind == 2:
            during.append({"fault": {"at": "row", "nth": rng.randint(1, 5), "signal": name}})
        elif kind == 3:  # while a resumed run rewrites metrics.csv's kept rows
            during.append({"fault": {"at": "rename", "file": "metrics.csv", "nth": 1, "signal": name, "torn": True}})
        else:
            during.append({"kill_after": (rng.uniform(0.05, 0.8), name)})
    final = [{"fault": {"at": "rename", "file": file, "nth": 1, "signal": "SIGKILL", "torn": torn}}
             for file, torn in (("actor.pt", True), ("critic.pt", False), ("summary.json", True))]
    final.append({"fault": {"at": "rename", "file": "actor.pt", "nth": 1, "signal": "SIGTERM", "torn": True}})
    return during, final


@pytest.mark.slow
def test_a_run_killed_at_any_moment_resumes_to_the_uninterrupted_files(tmp_path):
    """At least 20 kills (SIGKILL, SIGTERM, SIGINT) of one run, in checkpoint, metrics and weight
    writes and at random times; after each the folder is never damaged, and the run that is
    resumed each time ends with the uninterrupted run's metrics.csv and weights, byte for byte."""
    server = FaultServer(tmp_path / "sessions.log")
    try:
        assert server.session(tmp_path / "reference") == 0
        run = tmp_path / "run"
        during, final = fault_plan(random.Random(20261201))
        statuses = []
        for step in during:
            if (run / "summary.json").exists():
                break
            statuses.append(server.session(run, **step))
            assert rundir.state(run).kind in ("empty", "resumable"), (step, statuses)
        assert not (run / "summary.json").exists(), "the run finished before the faults of its final writes"
        for step in final:
            statuses.append(server.session(run, **step))
            assert rundir.state(run).kind in ("resumable", "finished"), (step, statuses)
        assert server.session(run) == 0
    finally:
        server.close()
    log = (tmp_path / "sessions.log").read_text()
    stopped = [s for s in statuses if s in (-signal.SIGKILL, 130, 143)]
    assert len(stopped) >= 20, (statuses, log[-3000:])
    assert {-signal.SIGKILL, 130, 143} <= set(statuses)
    assert "Traceback" not in log, log[-3000:]
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["resumed_at"]
    for name in ("metrics.csv", "actor.pt", "critic.pt"):
        assert (run / name).read_bytes() == (tmp_path / "reference" / name).read_bytes(), name
    assert not list(run.glob("*.tmp")) and not (run / CHECKPOINT_FILE).exists()


# ---- points 1-9 of the run-folder issue, each with its test ----

TINY = ["algo=spg", "er=recent", "episodes=3", "progress=false", "logger=none", "algo.minibatch_size=50"]


def train(overrides: list[str], folder: Path) -> dict:
    """A run as train.py makes it (with the settings it records), in this process."""
    from engine.config import RunConfig
    from engine.runner import train_population

    settings = RunConfig.compose_mapping(*overrides)
    return train_population(RunConfig.from_mapping(settings), folder, settings)[0]


@pytest.mark.slow
def test_a_finished_run_is_never_replaced_and_its_record_never_rewritten(tmp_path):
    """Points 1, 5 and the last of 9: a damaged summary is refused (not taken for an unfinished
    run); a refused command leaves .hydra/ as it was; a run ends with one line saying how it went
    and where its results are, also when its output goes to a file."""
    folder = tmp_path / "run"
    first = run_train(*TINY, f"hydra.run.dir={folder}")
    assert first.returncode == 0, first.stderr[-2000:]
    last = first.stdout.strip().splitlines()[-1]
    assert last.startswith("spg/recent seed 2067791: completed after 3 episodes, final performance ")
    assert last.endswith(f"results in {folder}")
    record = {p.name: p.read_bytes() for p in (folder / ".hydra").iterdir()}
    assert set(record) == {"config.yaml", "hydra.yaml", "overrides.yaml"}
    other = run_train(*TINY, "gamma=0.5", f"hydra.run.dir={folder}")
    assert other.returncode == 2 and "holds a finished run of a different configuration" in other.stderr
    assert {p.name: p.read_bytes() for p in (folder / ".hydra").iterdir()} == record  # point 5
    kept = {name: (folder / name).read_bytes() for name in ("metrics.csv", "actor.pt", "critic.pt")}
    summary = (folder / "summary.json").read_text()
    (folder / "summary.json").write_text(summary[:len(summary) // 2])  # truncated: no longer JSON
    damaged = run_train(*TINY, "gamma=0.5", f"hydra.run.dir={folder}")
    assert damaged.returncode == 2, damaged.stderr[-2000:]
    assert f"{folder} is damaged: {folder / 'summary.json'} is not JSON" in damaged.stderr
    assert "Traceback" not in damaged.stderr
    assert {name: (folder / name).read_bytes() for name in kept} == kept  # point 1
    assert {p.name: p.read_bytes() for p in (folder / ".hydra").iterdir()} == record


def test_damaged_folders_are_refused_with_the_file_and_the_reason(tmp_path):
    """Points 1 and 6 in process: every kind of damage is named; overwrite=true clears it."""
    from engine.config import ConfigError

    folder = tmp_path / "run"
    train([*TINY], folder)
    good = {name: (folder / name).read_bytes() for name in ("summary.json", "actor.pt", "critic.pt", "metrics.csv")}
    damages = [
        ("summary.json", b"", "summary.json is not JSON (empty)"),
        ("summary.json", b"[1, 2]", "summary.json holds a JSON list, not a summary"),
        ("summary.json", b'{"status": "completed"}', "summary.json lacks ['algo', 'er', 'seed'"),
        ("actor.pt", b"", "actor.pt is not the file its summary records (0 bytes where"),
        ("critic.pt", good["critic.pt"][:-1] + b"x", "critic.pt differs from the file its summary records"),
        ("metrics.csv", b"", "metrics.csv is not the file its summary records"),
    ]
    for name, content, reason in damages:
        (folder / name).write_bytes(content)
        with pytest.raises(ConfigError, match="is damaged") as refused:
            train([*TINY], folder)
        assert reason in str(refused.value), str(refused.value)
        assert (folder / name).read_bytes() == content  # left as it was
        (folder / name).write_bytes(good[name])
    (folder / "summary.json").unlink()  # weights without a summary or a checkpoint
    with pytest.raises(ConfigError, match="holds actor.pt and critic.pt but no summary.json"):
        train([*TINY], folder)
    summary = train([*TINY, "overwrite=true"], folder)
    assert summary["status"] == "completed" and (folder / "summary.json").exists()


def test_overwrite_removes_the_old_summary_before_the_new_run_starts(tmp_path):
    """Point 2: killed part way, an overwriting run leaves no old summary beside its new rows."""
    from analysis.report import read_run
    from tests.test_resilience import interrupted_after

    folder = tmp_path / "run"
    train([*TINY], folder)
    with interrupted_after(0):
        train([*TINY, "gamma=0.5", "overwrite=true", "checkpoint_every=1"], folder)
    assert not (folder / "summary.json").exists() and not (folder / "actor.pt").exists()
    assert read_run(folder).status == "partial"
    assert rundir.state(folder).kind == "empty"  # stopped before its first checkpoint: it starts afresh


def test_evaluation_settings_are_checked_before_training_and_a_checkpoint_takes_new_ones(tmp_path):
    """Point 3: a bad eval_seeds is refused before training; a run's checkpoint continues under
    other evaluation settings (they do not change what it trains)."""
    from engine.config import ConfigError, RunConfig
    from tests.test_resilience import interrupted_after

    with pytest.raises(ConfigError, match=r"eval_seeds must be track seeds in \[0, 2\*\*32\), got \[5000000000\]"):
        RunConfig.compose(*TINY, "eval_seeds=[5000000000]")
    folder = tmp_path / "run"
    with interrupted_after(1):
        train([*TINY, "eval_seeds=[1]", "eval_episodes=1", "checkpoint_every=1"], folder)
    summary = train([*TINY, "eval_seeds=[2]", "eval_episodes=1", "checkpoint_every=1"], folder)
    assert summary["resumed_at"] == 1 and list(summary["evaluation"]["tracks"]) == ["2"]
    assert summary["settings"]["eval_seeds"] == [2]


@pytest.mark.slow
def test_a_second_process_on_a_run_folder_is_refused_at_once(tmp_path):
    """Point 4: the folder's lock names its holder; the kernel releases it when the holder dies."""
    folder = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from engine import rundir\n"
                               f"with rundir.lock([{str(folder)!r}]):\n    print('held', flush=True); time.sleep(600)"],
                              cwd=ROOT, env=ENV, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        refused = run_train(*TINY, f"hydra.run.dir={folder}")
        assert refused.returncode == 2, refused.stderr[-2000:]
        assert f"{folder.resolve()} is in use by another process (pid {holder.pid} on " in refused.stderr
        assert not (folder / "metrics.csv").exists() and not (folder / ".hydra").exists()
        with pytest.raises(rundir.RunFolderBusy, match=f"pid {holder.pid}"):
            with rundir.lock([folder]):
                pass
    finally:
        holder.kill()
        holder.wait()
        holder.stdout.close()
    with rundir.lock([folder]):  # released by the kernel with the killed holder
        with rundir.lock([folder]):  # and re-entrant within one process
            pass
    (tmp_path / "a file").write_text("")
    with pytest.raises(rundir.RunFolderError, match="cannot use .* as a run folder"):  # a path checked first
        with rundir.lock([tmp_path / "a file" / "run"]):
            pass


def test_empty_and_hostile_files_get_one_clear_sentence(tmp_path):
    """Point 6 and 9's torch advice: empty checkpoints and weights, pickles with code, missing rows."""
    import datetime

    import torch

    from engine import checkpoint
    from engine.evaluation import RunFolderError, load_policy

    empty = tmp_path / "checkpoint.pt"
    empty.write_bytes(b"")
    with pytest.raises(checkpoint.CheckpointError, match=r"checkpoint.pt is empty \(0 bytes\)"):
        checkpoint.load(empty)
    hostile = tmp_path / "hostile.pt"
    torch.save({"version": checkpoint.VERSION, "when": datetime.date(2026, 12, 1)}, hostile)
    with pytest.raises(checkpoint.CheckpointError, match="refused unread, as loading them could run code") as err:
        checkpoint.load(hostile)
    assert "weights_only=False" not in str(err.value)
    with pytest.raises(RunFolderError, match="holds no finished run"):
        load_policy(tmp_path)


def test_report_and_evaluate_skip_a_damaged_run_and_go_on(tmp_path, capsys):
    """Point 6: a multi-folder evaluate.py and report.py skip a run whose actor.pt is empty."""
    import evaluate
    import report

    sweep = tmp_path / "sweep"
    train([*TINY], sweep / "spg" / "recent" / "seed2067791")
    broken = sweep / "spg" / "recent" / "seed773203"
    train([*TINY, "seed=773203"], broken)
    (broken / "actor.pt").write_bytes(b"")
    assert evaluate.main([str(sweep), "--episodes", "1"]) == 0
    captured = capsys.readouterr()
    assert f"skipped {broken}: {broken} is damaged: {broken / 'actor.pt'} is not the file its summary records" in \
        captured.err
    assert report.main([str(sweep), "--no-figures"]) == 0
    out = capsys.readouterr().out
    assert "1 damaged run(s), not in the tables:" in out and "(1 episodes" not in out


def test_a_checkpoint_without_its_rows_is_refused_clearly(tmp_path):
    """Point 9: a checkpoint beside a missing metrics.csv names the problem (was a RuntimeError)."""
    from engine.outputs import RunFolderError
    from tests.test_resilience import interrupted_after

    folder = tmp_path / "run"
    with interrupted_after(1):
        train([*TINY, "checkpoint_every=1"], folder)
    (folder / "metrics.csv").unlink()
    with pytest.raises(RunFolderError, match=r"metrics.csv is missing, but the run's checkpoint counts 1 episode rows"):
        train([*TINY, "checkpoint_every=1"], folder)


def test_command_line_options_and_their_errors(capsys):
    """Point 9: env.options={...} as conf/config.yaml shows it; a bad value names its key;
    final_window larger than episodes is said; evaluate.py's bad arguments fail at once."""
    import evaluate
    from engine.config import ConfigError
    from tests.test_config import load

    assert load("env.options={max_steps: 50, crash_penalty: 5}").env.options == {"max_steps": 50, "crash_penalty": 5}
    assert load("env.options.max_steps=60").env.episode_steps == 60
    assert load().env.options == {}  # the nulls of conf/config.yaml are the simulator's defaults
    for override, message in (("env.options.max_speed=a", "max_speed must be a number, got 'a'"),
                              ("env.options.ray_angles_deg=[a]", "ray_angles_deg must be a sequence of angles")):
        with pytest.raises(ConfigError, match=message):
            load(override)
    load("episodes=7", "final_window=9")
    assert "Note: final_window=9 is larger than episodes=7: the final performance is the mean of all 7" in \
        capsys.readouterr().err
    for args, message in ((["--tracks", "-1"], "argument --tracks: must be in [0, 4,294,967,295], got -1"),
                          (["--seed", "-1"], "argument --seed: must be in [0, 4,294,967,295], got -1"),
                          (["--video", "agent.avi"], "--video must name a .gif or .mp4 file, got 'agent.avi'"),
                          (["--table", str(ROOT)], f"--table {ROOT} is a folder; give a file name")):
        with pytest.raises(SystemExit) as exited:
            evaluate.main([str(ROOT), *args])
        assert exited.value.code == 2
        assert message in capsys.readouterr().err


def test_the_racing_config_keys_of_conf_are_the_simulators():
    """conf/config.yaml lists every RacingConfig field (as null) so that env.options={...} merges."""
    import dataclasses

    from omegaconf import OmegaConf

    from racing.config import RacingConfig

    options = OmegaConf.load(ROOT / "conf" / "config.yaml").env.options
    assert list(options) == [f.name for f in dataclasses.fields(RacingConfig)]
    assert all(value is None for value in options.values())


@pytest.mark.slow
def test_a_sweep_is_checked_whole_before_its_first_job_and_failures_are_listed_at_the_end(tmp_path):
    """Point 8: every bad job of a sweep is reported at once and nothing runs; two jobs on one
    folder are caught; a job that fails at run time is listed at the end, after the others finished."""
    sweep = tmp_path / "sweep"
    bad = run_train("-m", *TINY, "hydra/launcher=basic", "algo=spg,ppo", "gamma=0.9,2", "seed=1,5000000000", f"hydra.sweep.dir={sweep}")
    assert bad.returncode == 2, bad.stderr[-2000:]
    assert "The sweep was not started: 6 of its 8 jobs cannot run as given" in bad.stderr
    assert bad.stderr.count("seed must be in [0, 2**32)") == 4
    assert bad.stderr.count("gamma must be in [0, 1], got 2.0") == 2  # a job is reported with its first error
    assert not sweep.exists()
    same = run_train("-m", *TINY, "hydra/launcher=basic", "gamma=0.5,0.9", f"hydra.sweep.dir={sweep}")
    assert same.returncode == 2 and "writes " in same.stderr and "as job #0 (" in same.stderr
    (sweep / "spg" / "recent" / "seed7").mkdir(parents=True)  # a checkpoint of another run: refused at run time
    import torch

    from engine import checkpoint
    torch.save({"version": checkpoint.VERSION, "settings": {"seed": 7}, "members": [7]},
               sweep / "spg" / "recent" / "seed7" / CHECKPOINT_FILE)
    mixed = run_train("-m", *TINY, "seed=6,7", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={sweep}")
    assert mixed.returncode == 1, mixed.stderr[-2000:]
    assert "1 of 2 jobs did not finish" in mixed.stderr
    assert "job #1 (" in mixed.stderr and "checkpoint of a different configuration" in mixed.stderr
    assert json.loads((sweep / "spg" / "recent" / "seed6" / "summary.json").read_text())["status"] == "completed"


@pytest.mark.slow
def test_ctrl_c_ends_a_run_with_one_line_and_the_same_command_resumes(tmp_path):
    """Point 9: SIGINT stops the run at the end of its episode with a checkpoint and one line;
    point 4: the same command started again while it runs is refused, naming its pid."""
    folder = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "train.py"), *TINY, "episodes=100000", "checkpoint_every=50",
           f"hydra.run.dir={folder}"]  # far longer than the test: it stops on SIGINT
    proc = subprocess.Popen(cmd, cwd=ROOT, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_sigint_as_in_a_terminal)
    deadline = time.time() + 120
    while time.time() < deadline and not (folder / "metrics.csv").exists():
        time.sleep(0.05)
    second = run_train(*TINY, "episodes=100000", "checkpoint_every=50", f"hydra.run.dir={folder}")  # point 4
    assert second.returncode == 2 and f"is in use by another process (pid {proc.pid} on " in second.stderr
    assert proc.poll() is None  # the first goes on
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("Note:")]
    assert len(lines) == 1 and lines[0].startswith("Stopped by SIGINT after episode "), err[-2000:]
    episode = int(lines[0].split("after episode ")[1].split()[0])
    assert lines[0].endswith(f"saved at episode {episode} ({folder / CHECKPOINT_FILE}): the same command resumes "
                             "from there")
    assert len((folder / "metrics.csv").read_text().splitlines()) == episode + 1


def _mount_tmpfs(path: Path, size: str) -> None:
    path.mkdir(parents=True, exist_ok=True)
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], check=True,
                   capture_output=True)


def _can_mount() -> str | None:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return "needs root (and mount) to mount a small tmpfs as a full disk"
    return None


@pytest.mark.slow
@pytest.mark.skipif(_can_mount() is not None, reason=str(_can_mount()))
def test_a_full_disk_is_reported_as_such_and_leaves_the_last_good_files(tmp_path):
    """Point 7: on a tmpfs too small for the run, the error says no space (the path, the bytes
    needed and free), no temporary file is left, and no file is written in part."""
    from engine.outputs import DiskFull

    small = tmp_path / "small"
    try:
        _mount_tmpfs(small, "48k")  # metrics and the actor fit, the critic (47 kB) does not
        with pytest.raises(DiskFull, match=r"no space left on the device of .*critic.pt: writing it needs "
                                           r"[\d,]+ bytes, [\d,]+ are free") as full:
            train([*TINY, "checkpoint_every=0"], small / "run")
        assert "free some space and run the same command again" in str(full.value)
        left = sorted(p.name for p in (small / "run").iterdir())
        assert "critic.pt" not in left and "summary.json" not in left and not [n for n in left if n.endswith(".tmp")]
        assert len((small / "run" / "metrics.csv").read_text().splitlines()) == 4  # every row, whole
    finally:
        subprocess.run(["umount", str(small)], check=False)
    try:
        _mount_tmpfs(small, "64k")  # too small for the first checkpoint (replay memory): train.py's line
        result = run_train(*TINY, "er=hybrid", "checkpoint_every=1", f"hydra.run.dir={small / 'run'}")
        assert result.returncode == 1, result.stderr[-2000:]
        assert result.stderr.strip().splitlines()[-1].startswith(
            f"Stopped: no space left on the device of {small / 'run' / CHECKPOINT_FILE}: writing it needs ")
        assert "Traceback" not in result.stderr
        assert not list((small / "run").glob("*.tmp")) and not (small / "run" / CHECKPOINT_FILE).exists()
    finally:
        subprocess.run(["umount", str(small)], check=False)
