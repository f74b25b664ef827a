"""train.py end to end: run outputs, determinism, collectors, the parallel launcher (every table
cell runs in tests/test_readme.py)."""

import csv
import json
import os
import subprocess
from pathlib import Path

import pytest
import torch

from engine.outputs import EPISODE_COLUMNS
from engine.runner import train
from tests.test_config import load

ROOT = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "RL_LOGGING_LEVEL": "WARNING", "PYTHONWARNINGS": "ignore"}


def run_train(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """``python train.py ARGS`` (forked from a process that has imported torch: tests/zygote.py)."""
    from tests import zygote

    return zygote.run([ROOT / "train.py", *args], cwd=cwd, env=ENV, timeout=600)


def read_rows(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
def test_a_run_leaves_its_outputs(tmp_path):
    result = run_train("algo=spg_p", "er=hybrid", "seed=3", "episodes=3", "progress=false",
                       f"hydra.run.dir={tmp_path}")
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((tmp_path / "summary.json").read_text())
    for key in ("algo", "er", "seed", "episodes", "final_mean", "status", "wall_time_s"):
        assert key in summary
    assert (summary["algo"], summary["er"], summary["seed"], summary["status"]) == ("spg_p", "hybrid", 3, "completed")
    rows = read_rows(tmp_path / "metrics.csv")
    assert list(rows[0])[:len(EPISODE_COLUMNS)] == list(EPISODE_COLUMNS)
    final = sum(float(r["total_reward"]) for r in rows) / 3
    assert summary["final_mean"] == pytest.approx(final)
    actor = torch.load(tmp_path / "actor.pt", weights_only=True)
    assert actor["loc_head.weight"].shape == (2, 100)
    assert torch.load(tmp_path / "critic.pt", weights_only=True)
    assert list((tmp_path / "logs").rglob("*.csv"))  # TorchRL's CSV logger


def test_invalid_config_exits_with_one_clear_line(tmp_path):
    result = run_train("algo.actor_lr=-1", f"hydra.run.dir={tmp_path}")
    assert result.returncode == 2
    assert "Invalid configuration: algo spg_p_multi: actor_lr must be > 0, got -1.0" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "metrics.csv").exists()


def test_same_seed_same_metrics(tmp_path):
    cfg = load("algo=spg_p", "er=hybrid", "episodes=3", "progress=false", "logger=none")
    train(cfg, tmp_path / "a")
    train(cfg, tmp_path / "b")
    first = (tmp_path / "a" / "metrics.csv").read_bytes()
    assert first == (tmp_path / "b" / "metrics.csv").read_bytes()
    other = load("algo=spg_p", "er=hybrid", "episodes=3", "progress=false", "logger=none", "seed=5")
    train(other, tmp_path / "c")
    assert first != (tmp_path / "c" / "metrics.csv").read_bytes()


@pytest.mark.parametrize("algo, er", [("ppo_log", "memory"), ("spg_p", "recent")])
def test_both_collectors_train_identically(tmp_path, algo, er):
    """The fast direct collector changes nothing: metrics equal the TorchRL Collector's, bit for bit."""
    common = [f"algo={algo}", f"er={er}", "episodes=3", "progress=false", "logger=none"]
    train(load(*common, "env.collector=direct"), tmp_path / "direct")
    train(load(*common, "env.collector=torchrl"), tmp_path / "torchrl")
    assert (tmp_path / "direct" / "metrics.csv").read_bytes() == (tmp_path / "torchrl" / "metrics.csv").read_bytes()


@pytest.mark.slow
def test_parallel_launcher_reuses_workers_and_stays_deterministic(tmp_path):
    """Four jobs on two joblib workers: each equals the same run made alone in this process."""
    result = run_train("-m", "algo=spg_p,ppo", "er=recent", "seed=11,12", "episodes=2", "progress=false",
                       "logger=none", "hydra.launcher.n_jobs=2", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert result.returncode == 0, result.stderr[-3000:]
    for algo in ("spg_p", "ppo"):
        for seed in (11, 12):
            alone = tmp_path / "alone" / f"{algo}{seed}"
            train(load(f"algo={algo}", "er=recent", f"seed={seed}", "episodes=2", "progress=false",
                       "logger=none"), alone)
            swept = tmp_path / "sweep" / algo / "recent" / f"seed{seed}" / "metrics.csv"
            assert swept.read_bytes() == (alone / "metrics.csv").read_bytes(), (algo, seed)


@pytest.mark.slow
def test_a_finished_run_is_skipped_and_a_different_one_refused(tmp_path):
    from engine.outputs import seal

    args = ["algo=spg", "er=recent", "episodes=2", "progress=false", f"hydra.run.dir={tmp_path}"]
    assert run_train(*args).returncode == 0
    before = (tmp_path / "metrics.csv").read_bytes()
    again = run_train(*args, "logger=none")  # presentation keys do not make a different run
    assert again.returncode == 0 and "already completed" in again.stderr and "skipped" in again.stderr
    final = json.loads((tmp_path / "summary.json").read_text())["final_mean"]  # shown as the finished line shows it
    assert f"(final performance {final:.1f}, " in again.stderr and repr(final) not in again.stderr, again.stderr
    direct = run_train(*args, "env.collector=direct")  # nor the collector (the same batches), recorded or not
    assert direct.returncode == 0 and "already completed" in direct.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())
    summary["settings"]["env"]["collector"] = "direct"  # as runs recorded it when the setting was part of a run's
    (tmp_path / "summary.json").write_text(json.dumps(seal(summary)))
    assert "already completed" in run_train(*args).stderr
    other = run_train(*args[:-1], "episodes=3", f"hydra.run.dir={tmp_path}")
    assert other.returncode == 2
    assert "holds a finished run of a different configuration" in other.stderr
    assert (tmp_path / "metrics.csv").read_bytes() == before
    replaced = run_train(*args[:-1], "episodes=3", "overwrite=true", f"hydra.run.dir={tmp_path}")
    assert replaced.returncode == 0 and len(read_rows(tmp_path / "metrics.csv")) == 3


@pytest.mark.slow
def test_a_command_forked_from_the_test_zygote_is_a_new_process_run(tmp_path):
    """tests/zygote.py gives what ``python train.py ...`` gives: the same status, streams and files,
    a finished run and a refused one."""
    import subprocess
    import sys

    from tests import zygote

    def both(*args):
        real = subprocess.run([sys.executable, str(ROOT / "train.py"), *args, f"hydra.run.dir={tmp_path / 'real'}"],
                              cwd=ROOT, env=ENV, capture_output=True, text=True, timeout=600)
        forked = zygote.run([ROOT / "train.py", *args, f"hydra.run.dir={tmp_path / 'forked'}"], cwd=ROOT, env=ENV)
        same = str(tmp_path / "forked"), str(tmp_path / "real")  # the one difference asked for
        forked.stdout, forked.stderr = forked.stdout.replace(*same), forked.stderr.replace(*same)
        return real, forked

    real, forked = both("algo=spg_p", "er=hybrid", "seed=3", "episodes=2", "progress=false", "logger=none")
    assert real.returncode == forked.returncode == 0, (real.stderr[-2000:], forked.stderr[-2000:])
    assert (tmp_path / "real" / "metrics.csv").read_bytes() == (tmp_path / "forked" / "metrics.csv").read_bytes()
    assert real.stdout == forked.stdout and real.stderr == forked.stderr
    real, forked = both("algo=spg_p", "episodes=0")
    assert real.returncode == forked.returncode == 2 and real.stderr == forked.stderr and real.stderr
    # a sweep through the basic launcher (its jobs in the process itself) is forked too
    if zygote.forkable([ROOT / "train.py"]):  # (not with RACING_TEST_ZYGOTE=0 or without fork)
        assert zygote.forkable([ROOT / "train.py", "-m", "hydra/launcher=basic"])
    assert not zygote.forkable([ROOT / "train.py", "-m"])  # joblib's workers: a real process
    # (its one job equals the real process's run above: a sweep's job is the same run made alone)
    sweep = zygote.run([ROOT / "train.py", "-m", "hydra/launcher=basic", "algo=spg_p", "er=hybrid", "seed=3",
                        "episodes=2", "progress=false", "logger=none", f"hydra.sweep.dir={tmp_path / 'sweep'}"],
                       cwd=ROOT, env=ENV)
    assert sweep.returncode == 0, sweep.stderr[-2000:]
    assert ((tmp_path / "sweep" / "spg_p" / "hybrid" / "seed3" / "metrics.csv").read_bytes()
            == (tmp_path / "real" / "metrics.csv").read_bytes())


@pytest.mark.slow
def test_tests_that_differ_only_in_pytest_s_name_of_the_test_share_a_zygote(tmp_path):
    """pytest names the running test in PYTEST_CURRENT_TEST: a zygote per name would start one per test.
    One zygote serves them, and each child sees the environment it was given."""
    from tests import zygote

    if not zygote.forkable([ROOT / "train.py"]):
        pytest.skip("commands are not forked here (RACING_TEST_ZYGOTE=0 or no fork)")
    script = tmp_path / "show.py"
    script.write_text("import os\nprint(os.environ['PYTEST_CURRENT_TEST'], os.environ.get('RACING_PROBE'))\n")
    outputs = []
    for name in ("first", "second"):
        before = len(zygote._zygotes)
        result = zygote.run([script], cwd=tmp_path, env={**ENV, "PYTEST_CURRENT_TEST": name})
        outputs.append(result.stdout.split())
        if name == "second":
            assert len(zygote._zygotes) == before  # the first one's zygote
    assert outputs == [["first", "None"], ["second", "None"]]
    before = len(zygote._zygotes)  # any other variable still has a zygote of its own (it may be read at import)
    probed = zygote.run([script], cwd=tmp_path, env={**ENV, "PYTEST_CURRENT_TEST": "x", "RACING_PROBE": "1"})
    assert probed.stdout.split() == ["x", "1"]
    assert len(zygote._zygotes) == before + 1
