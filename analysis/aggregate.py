"""Interquartile mean with stratified bootstrap confidence intervals (Agarwal et al., 2021).

``scores`` is a matrix [samples, tasks]: each column holds one task's scores (here a task is a
track). The interquartile mean (IQM) drops the lowest and highest quarter of all scores
(``floor(n / 4)`` from each end, as ``scipy.stats.trim_mean(x, 0.25)``) and averages the rest.
The stratified bootstrap resamples, with replacement, the samples of each task separately,
so every resample keeps every task; the confidence interval is the percentile interval of
the statistic over the resamples.
"""

from __future__ import annotations

import numpy as np


def iqm(scores: np.ndarray) -> float:
    """Interquartile mean of all entries of ``scores``."""
    flat = np.sort(np.asarray(scores, dtype=np.float64).ravel())
    if flat.size == 0:
        raise ValueError("iqm of no scores")
    cut = flat.size // 4
    return float(flat[cut:flat.size - cut].mean())


def stratified_bootstrap_ci(scores: np.ndarray, statistic=iqm, reps: int = 2000, confidence: float = 0.95,
                            seed: int = 0) -> tuple[float, float, float]:
    """(statistic, low, high): the point estimate and its percentile bootstrap interval.

    ``scores`` [samples, tasks]; each resample draws ``samples`` rows with replacement within
    each task (column) independently.
    """
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 2 or 0 in scores.shape:
        raise ValueError(f"scores must be a non-empty [samples, tasks] matrix, got shape {scores.shape}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    rng = np.random.default_rng(seed)
    n, tasks = scores.shape
    rows = rng.integers(0, n, size=(reps, n, tasks))
    resampled = np.take_along_axis(scores[None].repeat(reps, axis=0), rows, axis=1)
    stats = np.array([statistic(r) for r in resampled])
    tail = (1 - confidence) / 2 * 100
    low, high = np.percentile(stats, [tail, 100 - tail])
    return statistic(scores), float(low), float(high)
