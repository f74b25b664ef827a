"""Compiled update steps (``compile=true``, ``learners/compiling.py``).

What holds, and is checked here: a compiled run is deterministic (also when the same process
compiled other runs before it); a compiled member trains
exactly as its compiled solo run (every reward, loss and weight), except one diagnostic, SPG's
``actor/q_target`` (the mean critic value of the chosen targets), whose mean over a minibatch
inductor reduces in another order for a population of one, so it may differ in its last bits
there; populations of any size agree in every column. SAC is the exception to the solo part: its
compiled population of one rounds differently (in training, not only a diagnostic); its members
agree in compiled populations of two or more. A machine without a C++ compiler runs
eagerly, says why once, and records it. Compiled and eager runs round differently: the report
keeps them apart (``tests/test_report.py``).
"""

import csv
import json
import math
import os
import warnings

import pytest
import torch

from engine.runner import train, train_population
from learners import compiling
from tests.test_config import load

REASON = compiling.unavailable_reason()
needs_compiler = pytest.mark.skipif(REASON is not None, reason=f"cannot compile here: {REASON}")
A, B, C = 2067791, 5468063, 773203
SOLO_ONLY = {"actor/q_target"}  # the one column a population of one may round differently


def common(algo, er, episodes=3):
    return [f"algo={algo}", f"er={er}", f"episodes={episodes}", "progress=false", "logger=none", "compile=true"]


def rows(folder):
    with open(folder / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.slow
@needs_compiler
def test_a_compiled_member_trains_as_its_compiled_solo_run_and_reruns_identically(tmp_path):
    algo, er = "spg_p_multi", "hybrid"  # SPG-p with replay and recent phases: every loss term and diagnostic
    train(load(*common(algo, er), f"seed={B}"), tmp_path / "solo")
    train_population(load(*common(algo, er), f"seeds=[{A},{B}]"), tmp_path / "ab")
    train_population(load(*common(algo, er), f"seeds=[{C},{B},{A}]"), tmp_path / "cba")
    train_population(load(*common(algo, er), f"seeds=[{A},{B}]"), tmp_path / "again")
    solo, member = rows(tmp_path / "solo"), rows(tmp_path / "ab" / f"seed{B}")
    assert [r.keys() for r in solo] == [r.keys() for r in member] and len(solo) == 3
    for mine, theirs in zip(solo, member):
        assert {k: v for k, v in mine.items() if k not in SOLO_ONLY} == \
               {k: v for k, v in theirs.items() if k not in SOLO_ONLY}
        for key in SOLO_ONLY & mine.keys():
            assert math.isclose(float(mine[key]), float(theirs[key]), rel_tol=1e-5, abs_tol=1e-6)
    for seed in (A, B):  # any population size and order, and a rerun in the same process: every column
        ab = (tmp_path / "ab" / f"seed{seed}" / "metrics.csv").read_bytes()
        assert ab == (tmp_path / "cba" / f"seed{seed}" / "metrics.csv").read_bytes()
        assert ab == (tmp_path / "again" / f"seed{seed}" / "metrics.csv").read_bytes()
    for name in ("actor", "critic"):
        solo_weights = torch.load(tmp_path / "solo" / f"{name}.pt")
        member_weights = torch.load(tmp_path / "ab" / f"seed{B}" / f"{name}.pt")
        assert all(torch.equal(solo_weights[k], member_weights[k]) for k in solo_weights)
    summary = json.loads((tmp_path / "ab" / f"seed{B}" / "summary.json").read_text())
    assert summary["compile"] == {"requested": True, "enabled": True, "reason": None,
                                  "cache": os.environ["TORCHINDUCTOR_CACHE_DIR"]}
    assert 0 < summary["time/compile_s"] <= summary["time/train_s"]

    # Eager steps round otherwise: the same first episode (it acts before any update), then close values.
    train(load(*common(algo, er)[:-1], f"seed={B}"), tmp_path / "eager")
    eager = rows(tmp_path / "eager")
    assert eager[0]["total_reward"] == solo[0]["total_reward"] and eager != solo
    first = {k: (float(solo[0][k]), float(eager[0][k])) for k in solo[0] if "/" in k}
    assert all(math.isclose(c, e, rel_tol=1e-3, abs_tol=1e-4) for c, e in first.values()), first


def test_without_a_compiler_a_run_says_why_and_runs_eagerly(tmp_path):
    from torch._inductor import config

    run = ["algo=spg", "er=recent", "episodes=2", "progress=false", "logger=none", f"seed={A}"]
    with config.patch({"cpp.cxx": (None, "no-such-c++-compiler")}), warnings.catch_warnings(record=True) as caught:
        assert "no C++ compiler 'no-such-c++-compiler' found" in compiling.unavailable_reason()
        warnings.simplefilter("always")
        train(load(*run, "compile=true"), tmp_path / "fallback")
    messages = [str(w.message) for w in caught if "compile=true" in str(w.message)]
    assert len(messages) == 1 and "running eagerly instead, because no C++ compiler" in messages[0]
    summary = json.loads((tmp_path / "fallback" / "summary.json").read_text())
    assert summary["compile"]["requested"] is True and summary["compile"]["enabled"] is False
    assert "no C++ compiler" in summary["compile"]["reason"] and "time/compile_s" not in summary
    train(load(*run), tmp_path / "eager")
    assert (tmp_path / "fallback" / "metrics.csv").read_bytes() == (tmp_path / "eager" / "metrics.csv").read_bytes()


def test_compile_is_validated():
    from engine.config import ConfigError

    with pytest.raises(ConfigError, match="compile"):
        load("compile=maybe")


@pytest.mark.slow
@needs_compiler
@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_sac_and_td3_train_compiled(tmp_path, algo, monkeypatch, capsys):
    """TorchRL's losses compile as one graph each (vmap over the Q-networks; no recompiles), and an
    SAC member trains the same in compiled populations of two and three, in any order (a compiled
    population of one rounds SAC otherwise, so ``processes`` never makes a part of one). An edit to the
    fused step's own code, which a compiled run does not run, is named (35048d1: TD3's ran silently)."""
    from learners import fast_paths

    edited = f"losses.{algo}.fused_{algo}_{'actor_losses' if algo == 'td3' else 'losses'}"
    monkeypatch.setattr(fast_paths, "_RECORD", {**fast_paths.recorded(), edited: "edited"})
    run = [f"algo={algo}", "er=memory", "episodes=2", "algo.td.warmup_episodes=1", "progress=false",
           "logger=none", "compile=true"]
    summary = train_population(load(*run, f"seeds=[{A},{B}]"), tmp_path / "ab")[0]
    assert (f"Note: {edited} changed, but this run's updates are the loss module's (compile=true compiles the loss "
            "module's step): that edit does not run here") in capsys.readouterr().err
    assert summary["paths"][0]["edits_not_run"] == [edited]
    monkeypatch.undo()
    assert summary["status"] == "completed" and summary["compile"]["enabled"]
    assert 0 < summary["time/compile_s"] <= summary["time/train_s"]
    assert all(math.isfinite(float(r["critic/loss_qvalue"])) for r in rows(tmp_path / "ab" / f"seed{A}")[1:])
    if algo == "td3":  # its population of one is its members' too: the SPG-p test's kind of check
        return
    train_population(load(*run, f"seeds=[{C},{B},{A}]"), tmp_path / "cba")
    for seed in (A, B):
        assert ((tmp_path / "ab" / f"seed{seed}" / "metrics.csv").read_bytes()
                == (tmp_path / "cba" / f"seed{seed}" / "metrics.csv").read_bytes())
