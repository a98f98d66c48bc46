"""Metrics of section 5.1.4 against hand-computed values; IQM and stratified bootstrap on known data."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from mira.experiments.metrics import (
    asymptotic_performance,
    final_window_mask,
    iqm,
    mean_std,
    oracle_threshold,
    sample_efficiency,
    sample_efficiency_over_seeds,
    stratified_bootstrap_ci,
)


def test_asymptotic_uses_rows_strictly_after_ninety_percent() -> None:
    steps = [100, 200, 300, 400, 500, 600, 700, 800, 900, 950, 1000]
    returns = [0, 1, 2, 3, 4, 5, 6, 7, 8, 10, 20]
    # step 900 is exactly 0.9·N and is NOT in the final 10%; 950 and 1000 are.
    assert asymptotic_performance(steps, returns, 1000) == pytest.approx(15.0)


def test_asymptotic_window_is_exact_for_large_budgets() -> None:
    # 0.9 * 30000 in floating point is 27000.000000000004; the window must still start after 27000.
    assert final_window_mask([26999, 27000, 27001, 30000], 30000) == [False, False, True, True]
    assert asymptotic_performance([27000, 28500, 30000], [100.0, 3.0, 5.0], 30000) == pytest.approx(4.0)


def test_asymptotic_falls_back_to_last_row_and_sorts() -> None:
    # Evaluations sparser than N/10: no row after 0.9·N → the last row alone.
    assert asymptotic_performance([400, 800], [1.0, 7.5], 1000) == 7.5
    # Rows are taken in step order whatever order they come in.
    assert asymptotic_performance([1000, 500, 950], [4.0, 100.0, 2.0], 1000) == pytest.approx(3.0)
    with pytest.raises(ValueError):
        asymptotic_performance([], [], 1000)


def test_oracle_threshold_positive_negative_zero() -> None:
    assert oracle_threshold(10_733.0) == pytest.approx(5366.5)
    assert oracle_threshold(-100.0) == pytest.approx(-150.0)  # half its magnitude BELOW the oracle
    assert oracle_threshold(0.0) == 0.0
    assert oracle_threshold(-100.0) <= -100.0


def test_sample_efficiency_first_crossing_and_never() -> None:
    steps = [1000, 2000, 3000, 4000, 5000]
    returns = [1.0, 4.9, 5.0, 2.0, 9.0]
    assert sample_efficiency(steps, returns, 5.0) == 3000  # >= counts; the later dip does not matter
    assert sample_efficiency(steps, returns, 9.0) == 5000
    assert sample_efficiency(steps, returns, 9.5) is None  # never reached
    assert sample_efficiency([], [], 0.0) is None
    assert sample_efficiency([3000, 1000, 2000], [9.0, 0.0, 9.0], 5.0) == 2000  # step order


def test_mean_std_and_sample_efficiency_over_seeds() -> None:
    assert mean_std([1.0, 2.0, 3.0]) == (2.0, 1.0)
    assert mean_std([4.0]) == (4.0, 0.0)
    m, s = mean_std([])
    assert math.isnan(m) and math.isnan(s)
    mean, std, reached, n = sample_efficiency_over_seeds([100, None, 300])
    assert (mean, reached, n) == (200.0, 2, 3)
    assert std == pytest.approx(math.sqrt(2) * 100)
    assert sample_efficiency_over_seeds([None, None]) == (None, None, 0, 2)


def test_iqm_hand_computed_and_matches_trim_mean() -> None:
    assert iqm([1, 2, 3, 4, 5, 6, 7, 8]) == pytest.approx(4.5)  # drop 2 each end: mean(3, 4, 5, 6)
    assert iqm([100, 0, 2, 1]) == pytest.approx(1.5)  # drop 1 each end: mean(1, 2)
    assert iqm([1, 2, 9]) == pytest.approx(4.0)  # floor(3/4) = 0: plain mean
    rng = np.random.default_rng(3)
    for n in (5, 10, 17, 40):
        x = rng.normal(size=n)
        assert iqm(x) == pytest.approx(stats.trim_mean(x, 0.25))
    assert math.isnan(iqm([]))


def test_bootstrap_constant_data_has_zero_width() -> None:
    point, low, high = stratified_bootstrap_ci([[3.0, 3.0, 3.0]], reps=500, seed=1)
    assert point == low == high == 3.0


def test_bootstrap_is_stratified() -> None:
    # Each replicate keeps four scores from each task, so the pooled sorted replicate is always
    # 0,0,0,0,1,1,1,1 and its IQM exactly 0.5: no width at all.
    point, low, high = stratified_bootstrap_ci({"a": [0, 0, 0, 0], "b": [1, 1, 1, 1]}, reps=2000, seed=0)
    assert (point, low, high) == (0.5, 0.5, 0.5)
    # Pooled into one stratum, resampling mixes the tasks and the interval opens up.
    _, low2, high2 = stratified_bootstrap_ci([[0, 0, 0, 0, 1, 1, 1, 1]], reps=2000, seed=0)
    assert low2 < 0.5 < high2


def test_bootstrap_seeded_and_plausible() -> None:
    rng = np.random.default_rng(0)
    data = rng.normal(10.0, 2.0, size=400)
    a = stratified_bootstrap_ci([data], reps=4000, seed=7)
    b = stratified_bootstrap_ci([data], reps=4000, seed=7)
    c = stratified_bootstrap_ci([data], reps=4000, seed=8)
    assert a == b and a != c
    point, low, high = a
    assert low < point < high
    # The mean's percentile CI ≈ mean ± 1.96·s/√n.
    mpoint, mlow, mhigh = stratified_bootstrap_ci([data], np.mean, reps=4000, seed=7)
    half = 1.96 * data.std(ddof=1) / math.sqrt(data.size)
    assert mpoint == pytest.approx(data.mean())
    assert (mhigh - mlow) / 2 == pytest.approx(half, rel=0.1)
    assert all(math.isnan(v) for v in stratified_bootstrap_ci([], reps=10))
