"""``analysis.aggregate``: rliable's estimators and stratified bootstrap intervals, held to rliable's own
numbers on the same data (``tests/data/rliable_reference.json``, written by ``tests/rliable_reference.py``
in an environment with rliable), to hand-computed values, and independent of the order runs come in."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from analysis import aggregate

REFERENCE = json.loads((Path(__file__).resolve().parent / "data" / "rliable_reference.json").read_text())
DATA = {name: np.array(m) for name, m in REFERENCE["data"].items()}


@pytest.mark.parametrize("key", sorted(REFERENCE["intervals"]))
def test_estimates_and_intervals_are_rliables(key):
    estimator, name = key.split(" | ")
    point, low, high = aggregate.stratified_bootstrap_ci(DATA[name], aggregate.ESTIMATORS[estimator],
                                                         reps=REFERENCE["reps"], seed=REFERENCE["seed"])
    assert [point, low, high] == pytest.approx(REFERENCE["intervals"][key], rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("key", sorted(REFERENCE["improvement"]))
def test_probability_of_improvement_and_its_interval_are_rliables(key):
    x, y = key.split(" | ")
    result = aggregate.probability_of_improvement_ci(DATA[x], DATA[y], reps=REFERENCE["reps"], seed=REFERENCE["seed"])
    assert list(result) == pytest.approx(REFERENCE["improvement"][key], rel=1e-12, abs=1e-12)


@pytest.mark.parametrize("name", sorted(REFERENCE["profiles"]))
def test_performance_profiles_are_rliables(name):
    ref = REFERENCE["profiles"][name]
    profile, low, high = aggregate.performance_profile(DATA[name], ref["taus"], reps=REFERENCE["profile_reps"],
                                                       seed=REFERENCE["seed"])
    for ours, theirs in ((profile, ref["profile"]), (low, ref["low"]), (high, ref["high"])):
        assert list(ours) == pytest.approx(theirs, rel=1e-12, abs=1e-12)


def test_hand_computed_values():
    scores = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0], [4.0, 40.0]])  # [runs, tasks]
    assert aggregate.iqm(scores) == pytest.approx(np.mean([3.0, 4.0, 10.0, 20.0]))  # 8 entries, 2 cut each end
    assert aggregate.mean(scores) == pytest.approx((2.5 + 25.0) / 2)
    assert aggregate.median(np.array([[1.0, 5.0, 9.0]])) == 5.0
    assert aggregate.optimality_gap(np.array([[0.5, 1.5]])) == pytest.approx(1 - (0.5 + 1.0) / 2)
    x, y = np.array([[1.0], [3.0]]), np.array([[2.0], [3.0]])
    # pairs (1,2) (1,3) (3,2) (3,3): above 1, tied 1 -> (1 + 0.5) / 4
    assert aggregate.probability_of_improvement(x, y) == pytest.approx(1.5 / 4)
    assert aggregate.probability_of_improvement(y, y) == 0.5
    profile, _, _ = aggregate.performance_profile(np.array([[0.2], [0.6], [0.9]]), [0.0, 0.5, 0.9], reps=10)
    assert list(profile) == pytest.approx([1.0, 2 / 3, 0.0])  # strictly above each tau


def test_an_interval_does_not_depend_on_the_order_of_the_runs():
    """The same runs read in another order gave other bounds (Monte-Carlo noise of resampling by position)."""
    scores = np.array([[141.2], [129.9], [150.3], [118.4], [133.0]])
    shuffled = scores[[3, 0, 4, 1, 2]]
    assert aggregate.stratified_bootstrap_ci(scores, reps=2000) == aggregate.stratified_bootstrap_ci(shuffled, reps=2000)
    assert aggregate.probability_of_improvement_ci(scores, scores + 1, reps=500) == \
        aggregate.probability_of_improvement_ci(shuffled, shuffled + 1, reps=500)


@pytest.mark.parametrize("bad", [np.zeros((0, 2)), np.zeros(3), np.array([[1.0, np.nan]])])
def test_bad_scores_are_refused(bad):
    with pytest.raises(ValueError, match="scores must be"):
        aggregate.stratified_bootstrap_ci(bad)


def test_iqm_by_hand():
    assert aggregate.iqm(np.arange(1.0, 9.0)) == 4.5  # drops 1, 2 and 7, 8
    assert aggregate.iqm([1.0, 2.0, 3.0, 4.0, 100.0]) == 3.0  # n=5: drops one from each end
    assert aggregate.iqm([[1.0, 3.0], [2.0, 1000.0]]) == 2.5  # all entries pooled
    with pytest.raises(ValueError):
        aggregate.iqm([])


def test_bootstrap_keeps_every_task_and_brackets_the_estimate():
    rng = np.random.default_rng(1)
    scores = rng.normal(100, 10, size=(20, 5)) + np.arange(5) * 20
    point, low, high = aggregate.stratified_bootstrap_ci(scores, reps=500, seed=3)
    assert point == aggregate.iqm(scores) and low < point < high
    assert aggregate.stratified_bootstrap_ci(scores, reps=500, seed=3) == (point, low, high)  # seeded


def test_constant_tasks_give_a_zero_width_interval():
    """Stratified: resampling within a column of equal values changes nothing."""
    scores = np.tile([10.0, 20.0, 30.0], (4, 1))
    assert aggregate.stratified_bootstrap_ci(scores, reps=200) == (20.0, 20.0, 20.0)
