"""Raw MCM diagnostics against hand-computed values on tiny fixed batches."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import integrate

from mira.mcm import metrics as M

LOG_2PI_E = math.log(2 * math.pi * math.e)


def kl_diag_gaussians(mu1: object, logstd1: object, mu2: object, logstd2: object) -> np.ndarray:
    """Per-state ``KL(N1 || N2)`` of diagonal Gaussians (the textbook closed form, summed over action
    dims): the reference the symmetric KL's simplified form is checked against."""
    m1, l1, m2, l2 = (np.asarray(x, dtype=np.float64) for x in (mu1, logstd1, mu2, logstd2))
    var1, var2 = np.exp(2.0 * l1), np.exp(2.0 * l2)
    return np.asarray(np.sum(l2 - l1 + (var1 + (m1 - m2) ** 2) / (2.0 * var2) - 0.5, axis=-1))


def test_diag_gaussian_entropy_hand_values() -> None:
    # Two unit-variance dims: 2 * ½ log(2πe); one dim with σ = 2: log 2 + ½ log(2πe).
    assert M.diag_gaussian_entropy(np.zeros(2)) == pytest.approx(LOG_2PI_E)
    out = M.diag_gaussian_entropy(np.array([[math.log(2.0)], [0.0]]))
    np.testing.assert_allclose(out, [math.log(2.0) + 0.5 * LOG_2PI_E, 0.5 * LOG_2PI_E])


def test_log_one_minus_tanh_sq_is_stable() -> None:
    u = np.array([0.0, 0.3, -2.0, 30.0, -400.0])
    ref = np.log(1.0 - np.tanh(u[:3]) ** 2)
    got = M.log_one_minus_tanh_sq(u)
    np.testing.assert_allclose(got[:3], ref, rtol=1e-12)
    assert np.all(np.isfinite(got))
    # For large |u|, 1 - tanh² ≈ 4 e^{-2|u|}.
    assert got[3] == pytest.approx(math.log(4.0) - 60.0)


def test_tanh_entropy_matches_quadrature_1d() -> None:
    mu, sigma = 0.5, 0.8
    dens = lambda u: math.exp(-0.5 * ((u - mu) / sigma) ** 2) / (sigma * math.sqrt(2 * math.pi))  # noqa: E731
    correction, _ = integrate.quad(lambda u: dens(u) * math.log(1 - math.tanh(u) ** 2), -12, 12)
    exact = math.log(sigma) + 0.5 * LOG_2PI_E + correction
    est = M.tanh_gaussian_entropy(np.array([[mu]]), np.array([[math.log(sigma)]]), 20000, np.random.default_rng(0))
    assert est.shape == (1,)
    assert est[0] == pytest.approx(exact, abs=0.01)
    assert est[0] < math.log(sigma) + 0.5 * LOG_2PI_E  # squashing loses entropy


def test_tanh_entropy_tiny_std_at_zero_is_gaussian_entropy() -> None:
    ls = np.full((3, 2), math.log(1e-4))
    est = M.tanh_gaussian_entropy(np.zeros((3, 2)), ls, 4, np.random.default_rng(1))
    np.testing.assert_allclose(est, M.diag_gaussian_entropy(ls), atol=1e-6)


def test_tanh_entropy_deterministic_given_rng() -> None:
    rng_mu = np.random.default_rng(3)
    mu, ls = rng_mu.normal(size=(5, 3)), rng_mu.normal(scale=0.3, size=(5, 3)) - 1
    a = M.tanh_gaussian_entropy(mu, ls, 8, np.random.default_rng(42))
    b = M.tanh_gaussian_entropy(mu, ls, 8, np.random.default_rng(42))
    np.testing.assert_array_equal(a, b)


def test_peg() -> None:
    assert M.d_peg(1.0, 2.0, 5000) == pytest.approx(-2e-4)
    with pytest.raises(ValueError):
        M.d_peg(1.0, 2.0, 0)


def test_sym_kl_known_gaussians() -> None:
    # N(0,1) vs N(1,1): each KL is ½, symmetric KL ½.
    assert M.sym_kl_diag_gaussians([[0.0]], [[0.0]], [[1.0]], [[0.0]]) == pytest.approx(0.5)
    # N(0,1) vs N(0,2²): KL12 = log 2 + 1/8 - 1/2, KL21 = -log 2 + 2 - 1/2, mean = 0.5625.
    kl12 = math.log(2) + 1 / 8 - 0.5
    kl21 = -math.log(2) + 2 - 0.5
    assert kl_diag_gaussians([0.0], [0.0], [0.0], [math.log(2)]) == pytest.approx(kl12)
    assert kl_diag_gaussians([0.0], [math.log(2)], [0.0], [0.0]) == pytest.approx(kl21)
    assert M.sym_kl_diag_gaussians([[0.0]], [[0.0]], [[0.0]], [[math.log(2)]]) == pytest.approx(0.5625)
    # Averaged over states (rows), summed over action dims (columns).
    mu1 = np.array([[0.0, 0.0], [0.0, 0.0]])
    mu2 = np.array([[1.0, 0.0], [0.0, 0.0]])
    ls2 = np.array([[0.0, 0.0], [math.log(2), 0.0]])
    assert M.sym_kl_diag_gaussians(mu1, np.zeros((2, 2)), mu2, ls2) == pytest.approx((0.5 + 0.5625) / 2)
    assert M.d_tpd(mu2, ls2, mu1, np.zeros((2, 2))) == pytest.approx((0.5 + 0.5625) / 2)


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-3, 3), min_size=3, max_size=3),
    st.lists(st.floats(-2, 1), min_size=3, max_size=3),
    st.lists(st.floats(-3, 3), min_size=3, max_size=3),
    st.lists(st.floats(-2, 1), min_size=3, max_size=3),
)
def test_sym_kl_properties(m1: list[float], l1: list[float], m2: list[float], l2: list[float]) -> None:
    a = M.sym_kl_diag_gaussians([m1], [l1], [m2], [l2])
    b = M.sym_kl_diag_gaussians([m2], [l2], [m1], [l1])
    assert a >= -1e-12
    assert a == pytest.approx(b)
    full = 0.5 * (kl_diag_gaussians(m1, l1, m2, l2) + kl_diag_gaussians(m2, l2, m1, l1))
    assert a == pytest.approx(float(full), rel=1e-9, abs=1e-12)
    assert M.sym_kl_diag_gaussians([m1], [l1], [m1], [l1]) == pytest.approx(0.0, abs=1e-12)


def test_pearson_known_series() -> None:
    assert M.pearson([1, 2, 3], [2, 4, 6], eps=0.0) == pytest.approx(1.0)
    assert M.pearson([1, 2, 3], [3, 2, 1], eps=0.0) == pytest.approx(-1.0)
    # cov = 1, var x = var y = 1.25 (population moments) -> r = 0.8; with ε the denominator is 1.25 + ε.
    assert M.pearson([1, 2, 3, 4], [1, 3, 2, 4], eps=0.0) == pytest.approx(0.8)
    assert M.pearson([1, 2, 3, 4], [1, 3, 2, 4], eps=0.25) == pytest.approx(1.0 / 1.5)
    assert M.d_pvc([1, 2, 3, 4], [1, 3, 2, 4], eps=0.0) == pytest.approx(0.8)
    assert M.pearson([5, 5, 5], [1, 2, 3]) == 0.0  # constant potential: decoupled, not NaN


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)), min_size=2, max_size=20))
def test_pearson_bounded(pairs: list[tuple[float, float]]) -> None:
    x, y = zip(*pairs, strict=True)
    r = M.pearson(x, y)
    assert -1.0 - 1e-9 <= r <= 1.0 + 1e-9


def test_jsd_known_distributions() -> None:
    assert M.jsd([1, 0], [0, 1]) == pytest.approx(math.log(2))
    assert M.jsd([0.3, 0.7], [0.3, 0.7]) == pytest.approx(0.0, abs=1e-15)
    # p = (½, ½), q = (1, 0), m = (¾, ¼).
    kl_pm = 0.5 * math.log(0.5 / 0.75) + 0.5 * math.log(0.5 / 0.25)
    kl_qm = math.log(1 / 0.75)
    assert M.jsd([0.5, 0.5], [1.0, 0.0]) == pytest.approx(0.5 * (kl_pm + kl_qm))
    assert M.jsd([1, 1], [2, 0]) == pytest.approx(0.5 * (kl_pm + kl_qm))  # renormalised


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(0, 10), min_size=4, max_size=4),
    st.lists(st.floats(0, 10), min_size=4, max_size=4),
)
def test_jsd_bounded_and_symmetric(p: list[float], q: list[float]) -> None:
    v = M.jsd(p, q)
    assert 0.0 <= v <= math.log(2) + 1e-12
    assert v == pytest.approx(M.jsd(q, p), abs=1e-12)


def test_d_fap_uses_renormalised_intersection() -> None:
    prev = {"a": 0.5, "b": 0.3, "c": 0.2}
    now = {"a": 0.6, "b": 0.4, "d": 0.9}
    assert M.d_fap(prev, now) == pytest.approx(M.jsd([0.625, 0.375], [0.6, 0.4]))
    assert M.d_fap(prev, {"a": 1.0, "z": 2.0}) == 0.0  # fewer than 2 shared factors
    assert M.d_fap({"a": 1.0, "b": 0.0}, {"b": 1.0, "a": 0.0}) == pytest.approx(math.log(2))


def test_d_rpe_hand_value() -> None:
    # targets y = r + γ(1 - term) Φ' = [0 + .5*2, 1 + .5*4, 2 + 0] = [1, 3, 2]
    # residuals Φ - y = [0, -1, -2] -> MSE 5/3; Var y = 2/3 -> RPE = 2.5
    val = M.d_rpe([1.0, 2.0, 0.0], [0.0, 1.0, 2.0], [2.0, 4.0, 6.0], 0.5, [0.0, 0.0, 1.0], eps=0.0)
    assert val == pytest.approx(2.5)
    # without the terminal mask the last target becomes 5: y = [1, 3, 5]
    no_term = M.d_rpe([1.0, 2.0, 0.0], [0.0, 1.0, 2.0], [2.0, 4.0, 6.0], 0.5, None, eps=0.0)
    assert no_term == pytest.approx((0 + 1 + 25) / 3 / (8 / 3))
