"""Every Hydra launcher the docs name runs a sweep to finished run folders.

basic, joblib and submitit_local (the submitit plugin's local executor: the job machinery of
SLURM without a cluster) each run the same two-job sweep; the SLURM preset is checked here as
Hydra composes it, and against a real SLURM in tests/test_slurm.py.
"""

import json

import pytest
import yaml
from hydra import compose, initialize_config_dir

from tests.test_train import ROOT, run_train

SWEEP = ["algo=spg", "er=recent", "seed=11,12", "episodes=2", "progress=false", "logger=none"]


def _sweep(launcher: str, sweep_dir) -> dict[int, bytes]:
    result = run_train("-m", f"hydra/launcher={launcher}", *SWEEP, f"hydra.sweep.dir={sweep_dir}")
    assert result.returncode == 0, result.stderr[-3000:]
    metrics = {}
    for seed in (11, 12):
        run_dir = sweep_dir / "spg" / "recent" / f"seed{seed}"
        summary = json.loads((run_dir / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["episodes"] == 2, launcher
        assert (run_dir / "actor.pt").exists() and (run_dir / ".hydra" / "config.yaml").exists()
        metrics[seed] = (run_dir / "metrics.csv").read_bytes()
    return metrics


@pytest.fixture(scope="module")
def basic_sweep(tmp_path_factory):
    return _sweep("basic", tmp_path_factory.mktemp("basic"))


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_launchers_run_the_same_sweep(tmp_path, basic_sweep, launcher):
    """Same runs, byte-identical results, whichever launcher ran them."""
    assert _sweep(launcher, tmp_path) == basic_sweep


@pytest.mark.slow
def test_a_population_splits_over_processes_inside_a_joblib_worker(tmp_path):
    """processes=2 in a joblib job: the parts are spawned from a loky worker (whose start method
    a spawned child cannot set: engine.processes.spawn_context)."""
    result = run_train("-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "algo=spg", "er=recent",
                       "seeds=[11,12]", "processes=2", "episodes=1", "progress=false", "logger=none",
                       f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    for seed in (11, 12):
        summary = json.loads((tmp_path / "spg" / "recent" / f"seed{seed}" / "summary.json").read_text())
        assert summary["status"] == "completed" and summary["population"] == {"seeds": [seed], "size": 1}
    # the joblib launcher's raw settings line is left out (on 258b7c4 every sweep printed it); its job lines stay
    assert "Joblib.Parallel(" not in result.stderr + result.stdout and "#0 : " in result.stderr + result.stdout
    # a configuration's note is said once per sweep (on 258b7c4: by the check, then again by each job's process)
    assert result.stderr.count("Note: final_window=20 is larger than episodes=1") == 1, result.stderr


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["submitit_local", "joblib"])
def test_a_sweep_run_again_launches_only_its_unfinished_jobs(tmp_path, launcher):
    """The sweep's check knows which jobs are finished (every member of the job's own settings): they are
    said skipped and not launched (on 258b7c4 a finished two-job joblib sweep took 11.5 s to start two
    workers that each skipped its job); a job added to the sweep runs under its own number."""
    _sweep(launcher, tmp_path)
    summary = tmp_path / "spg" / "recent" / "seed11" / "summary.json"
    before = summary.stat().st_mtime_ns, summary.read_bytes()
    jobs = len(list((tmp_path / ".submitit").iterdir())) if launcher == "submitit_local" else 0
    again = run_train("-m", f"hydra/launcher={launcher}", *SWEEP, f"hydra.sweep.dir={tmp_path}")
    assert again.returncode == 0 and again.stderr.count("already completed") == 2, again.stderr[-3000:]
    assert "Launching jobs" not in again.stderr + again.stdout
    assert (summary.stat().st_mtime_ns, summary.read_bytes()) == before
    if launcher == "submitit_local":
        assert len(list((tmp_path / ".submitit").iterdir())) == jobs  # no job submitted
    more = run_train("-m", f"hydra/launcher={launcher}", *[a.replace("seed=11,12", "seed=11,12,13") for a in SWEEP],
                     f"hydra.sweep.dir={tmp_path}")
    assert more.returncode == 0 and more.stderr.count("already completed") == 2, more.stderr[-3000:]
    hydra = yaml.safe_load((tmp_path / "spg" / "recent" / "seed13" / ".hydra" / "hydra.yaml").read_text())
    assert hydra["hydra"]["job"]["num"] == 2


def test_a_long_check_of_a_sweep_says_how_far_it_is(monkeypatch, capsys):
    """A whole-sweep check of 1,000 jobs took a minute with no output: a line every ten seconds says how many
    of them are checked."""
    import time

    from hydra_plugins.racing_launcher import sweeper

    clock = iter(range(0, 10_000, 4))  # four seconds a job
    monkeypatch.setattr(time, "monotonic", lambda: next(clock))
    for done in range(1, 11):
        sweeper._say_progress(done, 10)
    lines = capsys.readouterr().err.splitlines()
    assert lines == [f"Checking the sweep's jobs before any starts: {n} of 10 checked" for n in (4, 7)]


def test_slurm_preset_composes_with_its_defaults():
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=cpu"],
                      return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("SlurmLauncher")
    assert (launcher.partition, launcher.cpus_per_task, launcher.tasks_per_node) == ("cpu", 1, 1)
    assert launcher.timeout_min == 15 and launcher.max_num_timeout == 3 and launcher.mem_gb == 2
    assert "n_jobs" not in launcher


def test_joblib_stays_the_default_with_its_own_keys():
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("config", overrides=["hydra.launcher.n_jobs=2"], return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith("JoblibLauncher") and cfg.hydra.launcher.n_jobs == 2


@pytest.mark.slow
def test_clean_sweep_runs_an_export_of_the_commit(tmp_path):
    """clean_sweep.py runs HEAD's exported code (not the working tree's) and records its commit."""
    import subprocess
    import sys

    from engine.version import source_hash
    from tests.test_train import ENV

    if not (ROOT / ".git").exists():
        pytest.skip("clean_sweep.py exports commits: needs a git clone of the project")
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    code_dir, sweep = tmp_path / "code", tmp_path / "sweep"
    result = subprocess.run([sys.executable, str(ROOT / "clean_sweep.py"), "--code-dir", str(code_dir),
                             "algo=spg", "er=recent", "seed=11", "episodes=2", "progress=false", "logger=none",
                             f"hydra.sweep.dir={sweep}"], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert (code_dir / "engine" / "COMMIT").read_text().strip() == head
    summary = json.loads((sweep / "spg" / "recent" / "seed11" / "summary.json").read_text())
    assert summary["status"] == "completed"
    assert summary["code"] == {"commit": head, "dirty": None, "origin": "export", "source": source_hash(code_dir)}
    again = subprocess.run([sys.executable, str(ROOT / "clean_sweep.py"), "--code-dir", str(code_dir),
                            "--commit", "HEAD~1"], cwd=tmp_path, env=ENV, capture_output=True, text=True)
    assert again.returncode == 2 and "holds an export of another commit" in again.stderr


@pytest.mark.slow
def test_sweeps_started_together_export_the_same_commit_once(tmp_path):
    """Two sweeps of one commit launched at the same moment both get the export (no crash on a
    half-unpacked folder), and no partial copy is left behind."""
    from concurrent.futures import ThreadPoolExecutor

    import clean_sweep

    if not (ROOT / ".git").exists():
        pytest.skip("clean_sweep.py exports commits: needs a git clone of the project")

    commit = clean_sweep.resolve_commit("HEAD")
    code_dir = tmp_path / "code" / commit[:12]
    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(lambda _: clean_sweep.export(commit, code_dir), range(4)))
    assert results == [code_dir] * 4
    assert (code_dir / "engine" / "COMMIT").read_text().strip() == commit
    assert [p.name for p in code_dir.parent.iterdir()] == [code_dir.name]


def test_clean_sweep_knows_exports_of_commits_from_before_the_engine_package(tmp_path):
    """Commits before the engine package recorded their commit in experiment/COMMIT; their exports
    (e.g. the committed results' commit 8ee0bd8) are still recognised, and a folder without
    either file is not an export."""
    import clean_sweep

    (tmp_path / "old" / "experiment").mkdir(parents=True)
    (tmp_path / "old" / "experiment" / "COMMIT").write_text("8ee0bd8d86c8b4544c35463f6cf19c036a9dd50e\n")
    (tmp_path / "new" / "engine").mkdir(parents=True)
    (tmp_path / "new" / "engine" / "COMMIT").write_text("abc\n")
    assert clean_sweep.exported_commit(tmp_path / "old") == "8ee0bd8d86c8b4544c35463f6cf19c036a9dd50e"
    assert clean_sweep.exported_commit(tmp_path / "new") == "abc"
    assert clean_sweep.exported_commit(tmp_path) is None


def test_an_export_edited_by_hand_is_refused_not_run_under_the_commits_name(tmp_path):
    """A reused export is checked against the commit's archive: an added, changed or missing file is
    refused (found by a hostile trial: a planted train.py ran and its results carried the commit);
    compiled bytecode, which Python does not check against the source, is removed before a run."""
    import clean_sweep

    if not (ROOT / ".git").exists():
        pytest.skip("clean_sweep.py exports commits: needs a git clone of the project")
    commit = clean_sweep.resolve_commit("HEAD")
    code_dir = clean_sweep.export(commit, tmp_path / "code")
    original = (code_dir / "train.py").read_bytes()
    for edit, undo, words in (
            (lambda: (code_dir / "sitecustomize.py").write_text("import os\n"),
             lambda: (code_dir / "sitecustomize.py").unlink(), "sitecustomize.py was added"),
            (lambda: (code_dir / "train.py").write_bytes(original + b"\nprint('planted')\n"),
             lambda: (code_dir / "train.py").write_bytes(original), "train.py was changed"),
            (lambda: (code_dir / "train.py").unlink(), lambda: (code_dir / "train.py").write_bytes(original),
             "train.py is missing")):
        edit()
        with pytest.raises(clean_sweep.SweepError, match=words):
            clean_sweep.export(commit, code_dir)
        undo()
    (code_dir / "engine" / "__pycache__").mkdir(exist_ok=True)
    (code_dir / "engine" / "__pycache__" / "runner.cpython-311.pyc").write_bytes(b"planted")
    assert clean_sweep.export(commit, code_dir) == code_dir
    assert not (code_dir / "engine" / "__pycache__").exists()


@pytest.mark.slow
def test_an_ad_hoc_sweep_run_again_continues_in_its_folder(tmp_path):
    """``train.py -m ...`` without a folder went to a new dated folder each time, so running the same sweep
    again trained it again; its folder is now named by its command line, and the second run skips its runs."""
    from hydra_plugins.racing_launcher.sweeper import sweep_folder_name
    from tests.test_train import run_train

    args = ["-m", "algo=spg_p,ppo", "er=recent", "seed=2067791", "episodes=2", "progress=false", "logger=none",
            "hydra/launcher=basic"]
    first = run_train(*args, cwd=tmp_path)
    assert first.returncode == 0, first.stderr[-3000:]
    sweeps = list((tmp_path / "outputs" / "sweeps").iterdir())
    assert [p.name for p in sweeps] == [sweep_folder_name(args[1:-1])]  # the task overrides (not hydra/...)
    again = run_train(*args, cwd=tmp_path)
    assert again.returncode == 0 and again.stderr.count("already completed") == 2, again.stderr[-3000:]
    assert list((tmp_path / "outputs" / "sweeps").iterdir()) == sweeps
    assert sweep_folder_name(["a=1,2"]) != sweep_folder_name(["a=1", "2"]) and "/" not in sweep_folder_name(["x=/y"])


@pytest.mark.slow
def test_a_sweep_folder_that_cannot_be_resolved_is_one_line(tmp_path):
    """``hydra.sweep.dir=${hydra:...}`` (set by Hydra only inside a job) gave Hydra's traceback."""
    from tests.test_train import run_train

    result = run_train("-m", "algo=spg,ppo", "er=recent", "episodes=1", "hydra/launcher=basic",
                       "hydra.sweep.dir=" + str(tmp_path) + "/${hydra:job.name}", cwd=tmp_path)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("The sweep was not started: hydra.sweep.dir: "), lines


@pytest.mark.slow
def test_a_job_folder_no_launcher_can_resolve_is_refused_before_the_sweep(tmp_path):
    """``hydra.sweep.subdir=${oc.env:UNSET}`` was passed over by the whole-sweep check (as if a launcher would
    name it) and the sweep ended in joblib's traceback; a name a launcher resolves (its job id) still runs."""
    from tests.test_train import run_train

    common = ["-m", "algo=spg", "er=recent", "seed=1,2", "episodes=1", "progress=false", "logger=none"]
    result = run_train(*common, f"hydra.sweep.dir={tmp_path / 'a'}", "hydra.sweep.subdir=${oc.env:RACING_UNSET_X}")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr[-2000:]
    assert result.stderr.count("cannot be resolved: KeyError raised while resolving interpolation") == 2
    assert not (tmp_path / "a").exists()
    named = run_train(*common, f"hydra.sweep.dir={tmp_path / 'b'}", "hydra.sweep.subdir=s${hydra.job.id}")
    assert named.returncode == 0, named.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["multirun.yaml", "strain_0", "strain_1"]
