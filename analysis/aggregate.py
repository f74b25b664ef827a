"""Aggregate statistics as rliable computes them (Agarwal et al., 2021), in NumPy.

``scores`` is a matrix [runs, tasks]: column m holds the runs of task m (a task here is a track,
or, where each track has one run per cell, the cell's runs stacked as one task). The estimators
are rliable's (``rliable.metrics``): the interquartile mean of every entry (``floor(n / 4)``
dropped from each end, as ``scipy.stats.trim_mean(x, 0.25)``), the mean and the median of the
per-task means, the optimality gap, and the probability of improvement (per task, the
Mann-Whitney statistic P(X > Y) + P(X = Y) / 2, averaged over tasks). Their intervals are rliable's
stratified bootstrap (``rliable.library``): every resample draws each task's runs with replacement,
``numpy.random.RandomState(seed).choice`` once per resample as rliable draws them, and the interval
is the percentile interval of the statistic over the resamples (50,000 of them; 2,000 for
performance profiles, as rliable's defaults). ``tests/test_aggregate.py`` holds these numbers to
rliable's own on the same data (``tests/data/rliable_reference.json``, made by
``tests/rliable_reference.py`` with rliable installed).

One difference, on purpose: each task's runs are sorted before resampling, so an interval does not
depend on the order the runs were read in (rliable's does, by Monte-Carlo noise); on sorted input
the two are the same numbers.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

REPS = 50_000  # rliable's resamples for interval estimates
PROFILE_REPS = 2_000  # and for performance profiles


# Each estimator once, over a batch of score matrices [k, runs, tasks] -> [k] (the resamples of a bootstrap;
# the point estimate is a batch of one).

def _iqm(batch: np.ndarray) -> np.ndarray:
    flat = np.sort(batch.reshape(len(batch), -1), axis=1)
    cut = flat.shape[1] // 4
    return flat[:, cut:flat.shape[1] - cut].mean(axis=1)


def _mean(batch: np.ndarray) -> np.ndarray:
    return batch.mean(axis=1).mean(axis=1)


def _median(batch: np.ndarray) -> np.ndarray:
    return np.median(batch.mean(axis=1), axis=1)


def _optimality_gap(batch: np.ndarray, gamma: float = 1.0) -> np.ndarray:
    return gamma - np.minimum(batch, gamma).reshape(len(batch), -1).mean(axis=1)


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean of all entries of ``scores`` (rliable's ``aggregate_iqm``)."""
    flat = np.asarray(scores, dtype=np.float64).ravel()
    if flat.size == 0:
        raise ValueError("iqm of no scores")
    return float(_iqm(flat[None, :, None])[0])


def mean(scores: np.ndarray) -> float:
    """Mean of the per-task means (rliable's ``aggregate_mean``)."""
    return float(_mean(np.asarray(scores, dtype=np.float64)[None])[0])


def median(scores: np.ndarray) -> float:
    """Median of the per-task means (rliable's ``aggregate_median``)."""
    return float(_median(np.asarray(scores, dtype=np.float64)[None])[0])


def optimality_gap(scores: np.ndarray, gamma: float = 1.0) -> float:
    """How far below ``gamma`` the scores fall on average, each counted up to ``gamma`` (rliable's)."""
    return float(_optimality_gap(np.asarray(scores, dtype=np.float64)[None], gamma)[0])


ESTIMATORS: dict[str, Callable[[np.ndarray], float]] = {"IQM": iqm, "mean": mean, "median": median,
                                                       "optimality gap": optimality_gap}
_BATCHED = {iqm: _iqm, mean: _mean, median: _median, optimality_gap: _optimality_gap}


def _batched(statistic, resampled: np.ndarray) -> np.ndarray:
    """``statistic`` of each resample of ``resampled`` [reps, runs, tasks]: the estimators above in one pass,
    any other function one resample at a time."""
    if statistic in _BATCHED:
        return _BATCHED[statistic](resampled)
    return np.array([statistic(r) for r in resampled])


def _matrix(scores) -> np.ndarray:
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 2 or 0 in scores.shape:
        raise ValueError(f"scores must be a non-empty [runs, tasks] matrix, got shape {scores.shape}")
    if not np.isfinite(scores).all():
        raise ValueError("scores must be finite numbers")
    return np.sort(scores, axis=0)  # each task's runs in order: the interval does not depend on how they came


def _percentile_interval(stats: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray]:
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(stats, [tail, 100 - tail], axis=0)
    return low, high


def stratified_bootstrap_ci(scores, statistic=iqm, reps: int = REPS, confidence: float = 0.95,
                            seed: int = 0) -> tuple[float, float, float]:
    """(statistic, low, high): the point estimate and its percentile interval over ``reps`` stratified
    resamples (each task's runs drawn with replacement; rliable's ``get_interval_estimates``)."""
    scores = _matrix(scores)
    runs, tasks = scores.shape
    rng = np.random.RandomState(seed)
    stats = np.empty(reps)
    for start in range(0, reps, 5_000):  # bounded memory: 5,000 resamples at a time (one draw of them all is
        count = min(5_000, reps - start)  # the same stream as rliable's draw per resample)
        picks = rng.choice(runs, (count, runs, tasks), replace=True)
        stats[start:start + count] = _batched(statistic, scores[picks, np.arange(tasks)])
    low, high = _percentile_interval(stats, confidence)
    return float(statistic(scores)), float(low), float(high)


def probability_of_improvement(x, y) -> float:
    """P(X > Y) + P(X = Y) / 2 per task, averaged over tasks (rliable's, by the Mann-Whitney statistic);
    ``x`` [runs of X, tasks], ``y`` [runs of Y, tasks]."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or y.ndim != 2 or x.shape[1] != y.shape[1] or 0 in x.shape or 0 in y.shape:
        raise ValueError(f"x and y must be [runs, tasks] matrices of the same tasks, got {x.shape} and {y.shape}")
    above = (x[:, None, :] > y[None, :, :]).mean(axis=(0, 1))
    ties = (x[:, None, :] == y[None, :, :]).mean(axis=(0, 1))
    return float(np.mean(above + ties / 2))


def probability_of_improvement_ci(x, y, reps: int = REPS, confidence: float = 0.95,
                                  seed: int = 0) -> tuple[float, float, float]:
    """(P(X > Y), low, high): X's and Y's runs resampled independently within each task, X's first in each
    resample (rliable's ``StratifiedIndependentBootstrap``)."""
    x, y = _matrix(x), _matrix(y)
    point = probability_of_improvement(x, y)
    rng = np.random.RandomState(seed)
    tasks = np.arange(x.shape[1])
    if x.shape == y.shape:  # one draw per resample of X's and Y's indices together: rliable's stream
        both = rng.choice(x.shape[0], (reps, 2 * x.shape[0], x.shape[1]), replace=True)
        px, py = both[:, :x.shape[0]], both[:, x.shape[0]:]
    else:  # other bounds draw otherwise: one resample at a time
        draws = [(rng.choice(x.shape[0], x.shape, replace=True), rng.choice(y.shape[0], y.shape, replace=True))
                 for _ in range(reps)]
        px, py = np.stack([d[0] for d in draws]), np.stack([d[1] for d in draws])
    xs, ys = x[px, tasks], y[py, tasks]  # [reps, runs, tasks]
    above = (xs[:, :, None, :] > ys[:, None, :, :]).mean(axis=(1, 2))
    ties = (xs[:, :, None, :] == ys[:, None, :, :]).mean(axis=(1, 2))
    low, high = _percentile_interval((above + ties / 2).mean(axis=1), confidence)
    return point, float(low), float(high)


def performance_profile(scores, taus, reps: int = PROFILE_REPS, confidence: float = 0.95,
                        seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(profile, low, high) over ``taus``: the fraction of all runs scoring above each tau (rliable's
    score distribution), with its stratified bootstrap interval at each tau."""
    scores = _matrix(scores)
    taus = np.asarray(taus, dtype=np.float64)
    runs, tasks = scores.shape
    rng = np.random.RandomState(seed)
    picks = rng.choice(runs, (reps, runs, tasks), replace=True)
    resampled = scores[picks, np.arange(tasks)].reshape(reps, -1)
    stats = (resampled[:, :, None] > taus).mean(axis=1)  # [reps, taus]
    low, high = _percentile_interval(stats, confidence)
    return (scores.ravel()[:, None] > taus).mean(axis=0), low, high
