"""IQM and the stratified bootstrap against hand-computed values."""

import numpy as np
import pytest

from analysis.aggregate import iqm, stratified_bootstrap_ci


def test_iqm_by_hand():
    assert iqm(np.arange(1.0, 9.0)) == 4.5  # drops 1, 2 and 7, 8
    assert iqm([1.0, 2.0, 3.0, 4.0, 100.0]) == 3.0  # n=5: drops one from each end
    assert iqm([[1.0, 3.0], [2.0, 1000.0]]) == 2.5  # all entries pooled
    with pytest.raises(ValueError):
        iqm([])


def test_bootstrap_keeps_every_task_and_brackets_the_estimate():
    rng = np.random.default_rng(1)
    scores = rng.normal(100, 10, size=(20, 5)) + np.arange(5) * 20
    point, low, high = stratified_bootstrap_ci(scores, reps=500, seed=3)
    assert point == iqm(scores) and low < point < high
    assert stratified_bootstrap_ci(scores, reps=500, seed=3) == (point, low, high)  # seeded


def test_constant_tasks_give_a_zero_width_interval():
    """Stratified: resampling within a column of equal values changes nothing."""
    scores = np.tile([10.0, 20.0, 30.0], (4, 1))
    assert stratified_bootstrap_ci(scores, reps=200) == (20.0, 20.0, 20.0)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="samples, tasks"):
        stratified_bootstrap_ci(np.ones(5))
