"""Robust standardiser, KDE healthy model and stagnation band."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mira.mcm import HealthyModel, RobustStandardizer, stagnation_band, top_contributors


def test_standardizer_hand_values() -> None:
    s = RobustStandardizer(1, window=10, beta=0.5, min_history=5)
    for x in (1.0, 2.0, 3.0, 4.0, 5.0):
        z, sm = s.update([x])
        assert z[0] == 0.0 and sm[0] == 0.0  # fewer than 5 past values: no evidence yet
    z, sm = s.update([7.0])  # window [1..5]: median 3, MAD 1
    assert z[0] == pytest.approx(4.0 / 1.4826)
    assert sm[0] == pytest.approx(0.5 * 4.0 / 1.4826)


def test_standardizer_floor_clip_and_nan() -> None:
    s = RobustStandardizer(2, window=5, beta=0.0, min_history=2, z_clip=4.0)
    for _ in range(3):
        s.update([2.0, 0.0])
    z = s.standardize([2.001, 1.0])
    # scale = 1e-8 + 1e-3 * |2| for comp 0; comp 1 has floor 1e-8 -> clipped
    assert z[0] == pytest.approx(0.001 / (1e-8 + 2e-3))
    assert z[1] == 4.0
    z, _ = s.update([math.nan, 0.0])
    assert z[0] == 0.0
    assert len(s.state_dict()["hist"][0]) == 3  # NaN was not pushed


def test_standardizer_round_trip() -> None:
    rng = np.random.default_rng(0)
    a = RobustStandardizer(3, window=7)
    for _ in range(12):
        a.update(rng.normal(size=3))
    b = RobustStandardizer(1)
    b.load_state_dict(a.state_dict())
    for _ in range(10):
        x = rng.normal(size=3)
        za, sa = a.update(x)
        zb, sb = b.update(x)
        np.testing.assert_array_equal(za, zb)
        np.testing.assert_array_equal(sa, sb)


def _model(points: np.ndarray, h: float) -> HealthyModel:
    m = HealthyModel(points.shape[1], capacity=len(points))
    for p in points:
        m.insert(p)
    m.bandwidth = h
    return m


def test_log_density_hand_value_and_score() -> None:
    m = _model(np.array([[0.0, 0.0], [1.0, 0.0]]), 1.0)
    assert m.log_density([0.0, 0.0]) == pytest.approx(math.log((1 + math.exp(-0.5)) / 2))
    assert m.score([0.0, 0.0]) == pytest.approx(-math.log((1 + math.exp(-0.5)) / 2))
    far = m.score([1e3, 0.0])  # log-sum-exp keeps it finite
    assert math.isfinite(far) and far > 1e5


def test_median_heuristic_and_bandwidth_ema() -> None:
    m = _model(np.array([[0.0], [1.0], [3.0]]), 1.0)
    # pairwise distances 1, 3, 2 -> median 2; h = 2 / sqrt(2 log 4)
    expected = 2.0 / math.sqrt(2 * math.log(4.0))
    assert m.median_heuristic() == pytest.approx(expected)
    m.bandwidth = 1.0
    assert m.update_bandwidth() == pytest.approx(0.95 + 0.05 * expected)
    assert HealthyModel(2).median_heuristic() == 1.0


def test_fifo_eviction() -> None:
    m = HealthyModel(1, capacity=3)
    for v in range(5):
        m.insert([float(v)])
    assert len(m) == 3
    np.testing.assert_array_equal(m.points[:, 0], [2.0, 3.0, 4.0])
    with pytest.raises(ValueError):
        m.insert([math.nan])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.3, 3.0))
def test_gradient_matches_finite_differences(seed: int, h: float) -> None:
    rng = np.random.default_rng(seed)
    m = _model(rng.normal(size=(20, 5)), h)
    d = rng.normal(scale=1.5, size=5)
    g = m.grad_log_density(d)
    eps = 1e-5
    fd = np.array([(m.log_density(d + eps * e) - m.log_density(d - eps * e)) / (2 * eps) for e in np.eye(5)])
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-7)


def test_gradient_points_to_healthy_mass_and_top_m() -> None:
    m = _model(np.zeros((4, 3)), 1.0)
    g = m.grad_log_density([0.5, -3.0, 0.0])
    np.testing.assert_allclose(g, [-0.5, 3.0, 0.0])
    assert top_contributors(g, 2) == [1, 0]
    assert top_contributors([0.0, 1.0, -1.0], 2) == [1, 2]  # ties broken by index


def test_kde_round_trip() -> None:
    rng = np.random.default_rng(1)
    a = _model(rng.normal(size=(6, 2)), 0.7)
    b = HealthyModel(1)
    b.load_state_dict(a.state_dict())
    d = rng.normal(size=2)
    assert a.score(d) == b.score(d)
    np.testing.assert_array_equal(a.grad_log_density(d), b.grad_log_density(d))


def test_stagnation_band_unimodal_and_bimodal() -> None:
    # symmetric unimodal: the 50% shorth is median ± MAD (MAD of N(0,1) is 0.6745)
    c, h = stagnation_band(np.random.default_rng(5).standard_normal(20001))
    assert abs(c) < 0.05
    assert h == pytest.approx(0.6745, abs=0.03)
    # hand case: 7 values, windows of 4 -> shortest is [-1, -0.4, 0, 0.5] (length 1.5)
    assert stagnation_band([3.0, -3.0, -1.0, -0.4, 0.0, 0.5, 1.2]) == (pytest.approx(-0.2), pytest.approx(0.75))
    rng = np.random.default_rng(0)
    crouch = 0.45 + 0.01 * rng.standard_normal(300)
    falls = rng.uniform(0.1, 1.3, size=200)
    c, h = stagnation_band(np.concatenate([crouch, falls]))
    assert abs(c - 0.45) < 0.01
    assert 0.0 < h < 0.03
    assert stagnation_band([2.0]) == (2.0, 1e-3)
    with pytest.raises(ValueError):
        stagnation_band([math.nan])
