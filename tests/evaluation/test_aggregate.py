"""The aggregate estimators (Agarwal et al. 2021) against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from imitrl.evaluation.aggregate import (
    Interval,
    iqm,
    median,
    optimality_gap,
    performance_profile,
    probability_of_improvement,
    stratified_bootstrap,
    stratified_bootstrap_pair,
)


def test_iqm_trims_a_quarter_from_each_end():
    # 8 scores: floor(0.25 * 8) = 2 cut from each end -> mean(3, 4, 5, 6) = 4.5
    scores = np.array([[1.0, 8.0], [2.0, 7.0], [3.0, 6.0], [4.0, 5.0]])
    assert iqm(scores) == 4.5
    # 5 scores: floor(1.25) = 1 cut from each end -> mean(2, 3, 100) = 35
    assert iqm(np.array([[1.0], [2.0], [3.0], [100.0], [1000.0]])) == 35.0


def test_optimality_gap_and_median_by_hand():
    scores = np.array([[0.5, 1.2], [1.0, 0.0]])
    # gaps: 0.5, 0 (1.2 clipped to 1), 0, 1 -> mean 0.375
    assert optimality_gap(scores) == pytest.approx(0.375)
    assert optimality_gap(scores, gamma=2.0) == pytest.approx((1.5 + 0.8 + 1.0 + 2.0) / 4)
    assert median(np.array([[1.0, 3.0, 10.0], [3.0, 5.0, 0.0]])) == 4.0  # means 2, 4, 5


def test_probability_of_improvement_counts_ties_as_half():
    x = np.array([[1.0, 0.0], [2.0, 0.0]])
    y = np.array([[1.0, 1.0], [0.0, 1.0], [3.0, 1.0]])
    # task 0: pairs (1,1)=.5 (1,0)=1 (1,3)=0 (2,1)=1 (2,0)=1 (2,3)=0 -> 3.5 / 6; task 1: 0
    assert probability_of_improvement(x, y) == pytest.approx((3.5 / 6 + 0.0) / 2)
    assert probability_of_improvement(x, x) == 0.5


def test_performance_profile_is_the_fraction_above_each_threshold_per_task():
    scores = np.array([[0.1, 0.9], [0.5, 0.2], [0.9, 0.4], [0.3, 0.6]])
    profile = performance_profile(scores, [0.0, 0.35, 0.95])
    # tau 0.35: task 0 {0.5, 0.9} = 2/4, task 1 {0.9, 0.4, 0.6} = 3/4 -> 0.625
    assert profile.tolist() == [1.0, 0.625, 0.0]


def test_stratified_bootstrap_resamples_runs_within_each_task():
    scores = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])
    # every resample keeps task 0's zeros and task 1's ones: a degenerate interval
    assert stratified_bootstrap(scores, iqm, reps=50) == Interval(0.5, 0.5, 0.5)
    rng = np.random.default_rng(1)
    noisy = rng.normal(size=(10, 3))
    a = stratified_bootstrap(noisy, iqm, reps=500, seed=7)
    assert a == stratified_bootstrap(noisy, iqm, reps=500, seed=7)  # same seed, same digits
    assert a.low < a.point < a.high
    point, low, high = stratified_bootstrap(noisy, lambda s: performance_profile(s, [0, 1]))
    assert point.shape == (2,) and (low <= point).all() and (point <= high).all()
    pi = stratified_bootstrap_pair(noisy + 1.0, noisy, reps=300)
    assert pi.point > 0.5 and pi.low > 0.5


def test_bad_scores_are_refused():
    with pytest.raises(ValueError, match=r"\[runs, tasks\]"):
        iqm(np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        iqm(np.array([[np.nan]]))
    with pytest.raises(ValueError, match="same tasks"):
        probability_of_improvement(np.zeros((2, 2)), np.zeros((2, 3)))
