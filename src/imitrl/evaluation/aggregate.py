"""Aggregate scores across tasks and seeds: the estimators of Agarwal et al. (2021).

"Deep RL at the Edge of the Statistical Precipice" (NeurIPS 2021; the ``rliable``
package). A method's results are ``scores [R, T]``: one (normalised) score per run
``r`` and task ``t``, where a *run is a seed* (a trained learner), never an
evaluation episode. The point estimates:

* :func:`iqm`: interquartile mean, the mean of the middle 50% of all ``R * T`` scores
  (``scipy.stats.trim_mean(x, 0.25)``: ``floor(0.25 n)`` cut from each end);
* :func:`optimality_gap`: ``mean(gamma - min(x, gamma))``, how far below ``gamma``
  (default 1, the expert) the scores fall;
* :func:`probability_of_improvement`: ``P(X > Y)`` averaged over tasks, per task the
  Mann-Whitney statistic ``(1/(N M)) sum_{i,j} [x_i > y_j] + 0.5 [x_i = y_j]``;
* :func:`performance_profile`: for each threshold ``tau``, the fraction of runs with a
  score above it, averaged over tasks.

Intervals (:func:`stratified_bootstrap`): resample the runs of each task with
replacement, independently per task (the tasks are strata), recompute the estimate,
and take the ``(1 - c) / 2`` and ``(1 + c) / 2`` percentiles of the replicates (the
percentile bootstrap, ``rliable``'s default). Every draw comes from one seeded
``numpy.random.Generator``.

Why not ``rliable`` itself: it installs cleanly beside torch and numpy, but pulls in
pandas, scipy, statsmodels, arch and seaborn for these few lines; the estimators are
written here from their definitions and tested against hand-computed values.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Interval",
    "iqm",
    "mean",
    "median",
    "optimality_gap",
    "performance_profile",
    "probability_of_improvement",
    "stratified_bootstrap",
    "stratified_bootstrap_pair",
]


@dataclass(frozen=True)
class Interval:
    """A point estimate and its bootstrap interval."""

    point: float
    low: float
    high: float


def _scores(scores) -> np.ndarray:
    x = np.asarray(scores, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"scores must be [runs, tasks] with at least one of each, got {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("scores contain NaN or inf")
    return x


def iqm(scores) -> float:
    """Interquartile mean of every score ``[R, T]`` (``trim_mean(x, 0.25)`` over all)."""
    x = np.sort(_scores(scores).reshape(-1))
    cut = int(0.25 * x.size)
    return float(x[cut : x.size - cut].mean())


def mean(scores) -> float:
    """Mean of every score ``[R, T]``."""
    return float(_scores(scores).mean())


def median(scores) -> float:
    """Median over tasks of the per-task mean (``rliable.metrics.aggregate_median``)."""
    return float(np.median(_scores(scores).mean(axis=0)))


def optimality_gap(scores, gamma: float = 1.0) -> float:
    """``mean(gamma - min(x, gamma))`` over every score ``[R, T]``."""
    return float((gamma - np.minimum(_scores(scores), gamma)).mean())


def probability_of_improvement(x, y) -> float:
    """``P(X > Y)``: per task ``mean_{i,j} [x_i > y_j] + 0.5 [x_i = y_j]``, averaged over tasks.

    ``x [N, T]`` and ``y [M, T]``: runs of two methods on the same ``T`` tasks.
    """
    x, y = _scores(x), _scores(y)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"both methods need the same tasks: {x.shape[1]} and {y.shape[1]}")
    a, b = x[:, None, :], y[None, :, :]  # [N, M, T]
    per_task = ((a > b) + 0.5 * (a == b)).mean(axis=(0, 1))
    return float(per_task.mean())


def performance_profile(scores, taus: Sequence[float]) -> np.ndarray:
    """``[len(taus)]``: per ``tau``, the fraction of runs scoring above it, averaged over tasks."""
    x = _scores(scores)
    t = np.asarray(taus, dtype=np.float64)
    return (x[None, :, :] > t[:, None, None]).mean(axis=1).mean(axis=1)


def _resample(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The runs of each task drawn with replacement, independently per task."""
    runs, tasks = x.shape
    idx = rng.integers(0, runs, size=(runs, tasks))
    return np.take_along_axis(x, idx, axis=0)


def _percentiles(point, replicates: np.ndarray, confidence: float):
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    q = 100 * np.array([(1 - confidence) / 2, (1 + confidence) / 2])
    low, high = np.percentile(replicates, q, axis=0)
    return point, low, high


def stratified_bootstrap(
    scores,
    statistic: Callable[[np.ndarray], float | np.ndarray],
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> Interval | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``statistic(scores)`` and its stratified percentile-bootstrap interval.

    A scalar statistic gives an :class:`Interval`; a vector one (a performance
    profile) gives ``(point, low, high)`` arrays.
    """
    x = _scores(scores)
    if reps < 1:
        raise ValueError(f"reps must be positive, got {reps}")
    rng = np.random.default_rng(seed)
    replicates = np.stack([np.asarray(statistic(_resample(x, rng))) for _ in range(reps)])
    point, low, high = _percentiles(np.asarray(statistic(x)), replicates, confidence)
    if np.ndim(point) == 0:
        return Interval(float(point), float(low), float(high))
    return point, low, high


def stratified_bootstrap_pair(
    x,
    y,
    statistic: Callable[[np.ndarray, np.ndarray], float] = probability_of_improvement,
    *,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
) -> Interval:
    """``statistic(x, y)`` (default: probability of improvement) with both methods' runs
    resampled independently, per task."""
    x, y = _scores(x), _scores(y)
    rng = np.random.default_rng(seed)
    replicates = np.array([statistic(_resample(x, rng), _resample(y, rng)) for _ in range(reps)])
    point, low, high = _percentiles(statistic(x, y), replicates, confidence)
    return Interval(float(point), float(low), float(high))
