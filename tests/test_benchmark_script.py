"""The speed benchmark runs and prints its table (numbers are not asserted: speed is not a test)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from tests import zygote

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_env_speed_benchmark_prints_its_table():
    result = zygote.run(["-m", "speed.env_speed", "--seconds", "0.01", "--max-cars", "64"],
                        cwd=ROOT, env=dict(os.environ), timeout=300)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    assert len(rows) == 1 + 11  # header and one row per implementation and size up to 64 cars
    assert "| TorchRL env, step_and_maybe_reset | 64 |" in result.stdout
    assert "| Gymnasium native vector env (make_vec) | 64 |" in result.stdout
    assert "| 1024 |" not in result.stdout


@pytest.mark.slow
def test_train_speed_benchmark_prints_its_tables():
    result = zygote.run(["-m", "speed.train_speed", "--episodes", "2", "--repeats", "2",
                         "--cells", "ppo/recent", "spg_p/hybrid", "--pairs", "1"],
                        cwd=ROOT, env=dict(os.environ), timeout=600)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    assert len(rows) == (1 + 2) + (1 + 5) + (1 + 2 + 1)
    assert "| Collector, as a run uses it |" in result.stdout
    runs = [row.split("|") for row in rows if row.startswith(("| ppo/recent", "| spg_p/hybrid"))]
    assert [row[5].strip() for row in runs] == ["yes", "yes"]  # both collectors wrote the same metrics.csv


@pytest.mark.slow
def test_population_speed_benchmark_prints_its_tables():
    from learners.compiling import unavailable_reason

    # Both modes where a C++ compiler is present (a solo run, to keep the test short), else eager populations.
    sizes = ["--sizes", "1", "--modes", "eager", "compiled"] if unavailable_reason() is None else ["--sizes", "1", "2"]
    result = zygote.run(["-m", "speed.population_speed", "--episodes", "2",
                         "--cells", "ppo/recent", "--collectors", "2", "--processes", "2", *sizes],
                        cwd=ROOT, env=dict(os.environ), timeout=600)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    assert len(rows) == (1 + 2) + (1 + 1) + (1 + 1)
    assert "| ppo/recent | 1 | eager | 2 |" in result.stdout or "| ppo/recent | 2 | eager | 2 |" in result.stdout
    assert "matmul peak here" in result.stdout
    assert "| ppo/recent | 1 | compiled |" in result.stdout or "| ppo/recent | 2 | eager |" in result.stdout


@pytest.mark.slow
def test_numerics_speed_benchmark_prints_its_table():
    result = zygote.run(["-m", "speed.numerics_speed", "--episodes", "1",
                         "--members", "2", "--cells", "ppo/recent", "--repeats", "1"],
                        cwd=ROOT, env=dict(os.environ), timeout=600)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    from speed.numerics_speed import SHAPES

    assert len(rows) == (1 + 3 * len(SHAPES)) + (1 + 1) and "| ppo/recent | 2 |" in result.stdout
    assert "| fma | portable | native | fma / native | portable / fma |" in result.stdout
    assert "portable: " in result.stdout and "MKL COMPATIBLE" in result.stdout
    assert "FMA peak of one core (GFLOP/s, measured)" in result.stdout
    assert "| hidden 100x100, minibatch 200 | 2 | weight grad |" in result.stdout


@pytest.mark.slow
def test_oracle_convergence_benchmark_prints_its_table():
    result = zygote.run(["-m", "speed.oracle_convergence", "--tracks", "1001", "--episodes",
                         "1", "--horizon", "5", "--iterations", "1", "--candidates", "16", "--ladder", "1"],
                        cwd=ROOT, env=dict(os.environ), timeout=300)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    assert len(rows) == 1 + 2 and rows[1].startswith("| base |") and rows[2].startswith("| candidates=4 |")


@pytest.mark.slow
def test_oracle_circuit_benchmark_prints_its_table():
    result = zygote.run(["-m", "speed.oracle_circuit", "--points", "100", "--steps", "2"],
                        cwd=ROOT, env=dict(os.environ), timeout=300)
    assert result.returncode == 0, result.stderr
    rows = result.stdout.splitlines()[2:]
    assert rows[0].startswith("generated (seed 1001)") and rows[0].endswith("1.00")
    assert rows[1].startswith("circuit (100 points)") and " 100 " in rows[1]


@pytest.mark.slow
def test_recipe_cost_benchmark_prints_its_table():
    result = zygote.run(["-m", "speed.recipe_cost", "--sizes", "1", "--steps", "2",
                         "--recipes", "sac", "sac-module", "droq", "droq-module"], cwd=ROOT, env=dict(os.environ), timeout=300)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith("| ")]
    assert len(rows) == 1 + 4
    assert "| sac | algo=sac | 1 | 1 | 39200 |" in result.stdout
    assert "| sac-module | algo=sac | 1 | 1 | 39200 |" in result.stdout  # the same run, its step unfused  # before each episode after the 5 of warm-up
    assert "| droq | algo=droq | 1 | 5 | 196000 |" in result.stdout


def test_recipe_cost_says_n_a_where_noise_hid_the_step(monkeypatch, capsys):
    """A measurement that came out empty (the longer run no slower) is printed as n/a, not 0.0 ms."""
    from speed import recipe_cost
    from engine.config import RunConfig

    td = RunConfig.compose("algo=sac").algo.td
    monkeypatch.setattr(recipe_cost, "measure", lambda *a, **k: {"step": None, "episode": 0.1, "td": td,
                                                                 "episodes": 201})
    assert recipe_cost.main(["--sizes", "1", "--recipes", "sac"]) == 0
    out = capsys.readouterr().out
    assert "| sac | algo=sac | 1 | 1 | 39200 | n/a (noise: more --steps) |" in out and "| 0.0 |" not in out


@pytest.mark.slow
def test_floor_benchmark_prints_its_table():
    result = zygote.run(["-m", "speed.floor", "--sizes", "1", "2", "--steps", "2",
                         "--learners", "sac", "ppo"], cwd=ROOT, env=dict(os.environ), timeout=300)
    assert result.returncode == 0, result.stderr
    rows = [line.split(" | ") for line in result.stdout.splitlines() if line.startswith("| ")][1:]
    assert [(r[0], r[2], r[3]) for r in rows] == [("| sac", "1", "step"), ("| sac", "2", "step"),
                                                  ("| ppo", "1", "phase (60 steps)"), ("| ppo", "2", "phase (60 steps)")]
    products = [int(r[-1].rstrip(" |")) for r in rows]
    # members are stacked: a step makes the same products whatever R (one call per layer and pass)
    assert products[0] == products[1] > 0 and products[2] == products[3] > 0
    assert all(float(r[7].rstrip("x")) > 1.0 for r in rows)  # a step costs more than its products alone


def test_floor_records_a_layers_products_and_replays_them():
    import torch

    from speed.floor import Recorder, replay
    from learners import kernels
    from learners.networks import StackedMLP

    if not kernels.active():
        pytest.skip(f"the project's kernels are not in use here: {kernels.unavailable_reason()}")
    recorder = Recorder()
    undo = recorder.install()
    try:
        net = StackedMLP(3, [6, 8, 1], "tanh", linear_output=True)
        x = torch.randn(3, 5, 6)
        recorder.on = True
        net(x).sum().backward()
        recorder.on = False
    finally:
        undo()
    calls = recorder.calls[0]
    kinds = [c[0] for c in calls]
    # two forward products, two weight gradients, one input gradient (x needs none), two bias sums
    assert kinds.count("gemm") == 5 and kinds.count("colsum") == 2
    assert all(c[2][0] == 3 for c in calls if c[0] == "gemm")  # the three members in every call
    assert replay(calls, repeats=1) > 0.0
    assert replay(calls * 50, repeats=1, budget=1) > 0.0  # a chunk per call: memory bounded whatever the steps


@pytest.mark.slow
def test_floor_times_the_paper_phases_fused_and_through_the_loss_module():
    """``--module``'s second row for SPG and PPO is the loss module's phase: the same products (the
    fused steps make the products the module makes), taken without the fused steps."""
    from speed.floor import measure
    from learners import kernels

    if not kernels.active():
        pytest.skip(f"the project's kernels are not in use here: {kernels.unavailable_reason()}")
    fused, module = (measure(["algo=ppo", "er=recent"], False, 2, 2, fused=f) for f in (True, False))
    assert fused["fused"] and not module["fused"]
    assert fused["products"] == module["products"] > 0 and fused["steps"] == module["steps"] == 60


def test_floor_says_why_without_the_kernels(monkeypatch, capsys):
    from speed import floor
    from learners import kernels

    monkeypatch.setattr(kernels, "active", lambda: False)
    assert floor.main(["--sizes", "1", "--learners", "sac"]) == 1
    assert "not in use here" in capsys.readouterr().out


@pytest.mark.parametrize("args", [["--sizes", "0"], ["--sizes", "1001"], ["--steps", "-1"], ["--steps", "5001"],
                                  ["--steps", "x"]])
def test_the_step_benchmarks_refuse_sizes_they_cannot_measure_in_one_line(args, capsys):
    """A population of 0 or beyond the ceiling, or a step count that would record without end, is
    refused before anything runs (it ended in a traceback, or in gigabytes of recorded products)."""
    from speed import floor, recipe_cost

    for tool in (floor, recipe_cost):
        with pytest.raises(SystemExit) as stop:
            tool.main(args)
        assert stop.value.code == 2 and "expected a whole number from 1 to" in capsys.readouterr().err


@pytest.fixture(scope="module")
def tiny_sac_run(tmp_path_factory):
    from tests.test_train import run_train

    folder = tmp_path_factory.mktemp("evaluation_speed") / "sac"
    result = run_train("algo=sac", "er=memory", "episodes=2", "env.options.max_steps=20", "progress=false",
                       f"hydra.run.dir={folder}")
    assert result.returncode == 0, result.stderr
    return folder


@pytest.mark.slow
def test_evaluation_speed_benchmark_prints_its_table(tiny_sac_run):
    result = zygote.run(["-m", "speed.evaluation_speed", str(tiny_sac_run), "--steps", "2", "--rounds", "1"],
                        cwd=ROOT, env=dict(os.environ), timeout=300)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[1].split()[:2] == ["run", "1"] and len(lines) == 3
    assert float(lines[2].split()[-1]) > 0  # the default's time over one thread's
    refused = zygote.run(["-m", "speed.evaluation_speed", str(tiny_sac_run.parent)], cwd=ROOT,
                         env=dict(os.environ), timeout=300)
    assert refused.returncode == 2 and "is not a finished run folder" in refused.stderr


@pytest.mark.slow
def test_a_policy_loaded_without_a_mode_runs_its_runs_numerics_on_one_thread(tiny_sac_run):
    """A library caller (a notebook) that set no numerics mode gets the run's own from load_policy."""
    import subprocess
    import sys

    code = ("import sys; from engine import numerics; from engine.evaluation import load_policy; "
            "load_policy(sys.argv[1]); import torch; print(numerics.applied(), torch.get_num_threads())")
    env = {k: v for k, v in os.environ.items() if k not in ("ATEN_CPU_CAPABILITY", "MKL_CBWR")}
    result = subprocess.run([sys.executable, "-c", code, str(tiny_sac_run)], cwd=ROOT, capture_output=True,
                            text=True, env=env)
    # torch loaded before the mode could be set: the run's fma numerics are refused with the remedy
    assert result.returncode != 0 and "Start a new process" in result.stderr, result.stderr
    result = subprocess.run([sys.executable, "-c", code, str(tiny_sac_run)], cwd=ROOT, capture_output=True,
                            text=True, env={**env, "ATEN_CPU_CAPABILITY": "avx2", "MKL_CBWR": "COMPATIBLE",
                                            "OMP_NUM_THREADS": "2"})
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["fma", "1"]
