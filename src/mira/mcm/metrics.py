"""Raw diagnostic metrics of section 4.3.1, as pure NumPy functions.

Every function here is stateless and side-effect free: the monitor (``monitor.py``) keeps whatever
it needs from the previous cycle (previous entropy, previous attention) and calls these on plain
arrays, so each metric can be unit-tested against a hand-computed value and reused by the trainer
(for example to compute the mean policy entropy it puts into a ``CycleSnapshot``).

Conventions
-----------
* Policy statistics are per-state arrays ``[N, act_dim]``: the mean and the log standard deviation
  of a diagonal Gaussian. For SAC these are the pre-squash (``u``-space) parameters of the
  tanh-squashed Gaussian ``a = tanh(u)``; for DDPG a Gaussian surrogate (section 4.3.1): the mean is
  the deterministic action, the standard deviation the exploration noise (``DDPG.policy_stats``).
* All logarithms are natural; entropies and divergences are in nats.
* Reductions over states are plain means, matching the expectations ``E_{s ~ D_k}`` of the paper.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

PVC_EPS = 1e-8
"""``ε`` of eq. (16): keeps the correlation finite, and near 0, when Φ or the value is constant."""
RPE_EPS = 1e-8
"""``ε`` of eq. (18): keeps the ratio finite when the target has no variance."""

_HALF_LOG_2PI_E = 0.5 * np.log(2.0 * np.pi * np.e)
_LOG2 = float(np.log(2.0))


def _as_f64(x: ArrayLike) -> FloatArray:
    return np.asarray(x, dtype=np.float64)


# --------------------------------------------------------------------------------------------------
# Policy entropy
# --------------------------------------------------------------------------------------------------


def diag_gaussian_entropy(log_std: ArrayLike) -> FloatArray:
    """Entropy of a diagonal Gaussian per state, ``sum_j (log σ_j + ½ log 2πe)``.

    ``log_std`` has shape ``[..., act_dim]``; the result has shape ``[...]`` (one entropy per state).
    The mean does not enter: a Gaussian's entropy depends only on its covariance.
    """
    ls = _as_f64(log_std)
    return np.sum(ls + _HALF_LOG_2PI_E, axis=-1)


def log_one_minus_tanh_sq(u: ArrayLike) -> FloatArray:
    """``log(1 - tanh(u)^2)`` without cancellation for large ``|u|``.

    Uses the identity ``1 - tanh(u)^2 = 4 e^{-2|u|} / (1 + e^{-2|u|})^2``, i.e.
    ``2 (log 2 - |u| - log1p(e^{-2|u|}))``, which stays finite where ``tanh(u)`` rounds to ±1.
    """
    a = np.abs(_as_f64(u))
    return 2.0 * (_LOG2 - a - np.log1p(np.exp(-2.0 * a)))


def tanh_gaussian_entropy(mean: ArrayLike, log_std: ArrayLike, n_samples: int, rng: np.random.Generator) -> FloatArray:
    """Monte-Carlo estimate of the entropy of ``a = tanh(u)``, ``u ~ N(mean, diag(exp(log_std)^2))``.

    The squashed entropy has no closed form. By the change of variables ``p_a(a) = p_u(u) / |det J|``
    with ``J = d tanh / du = diag(1 - tanh(u)^2)``::

        H[a] = H[u] + E_u[ log |det J(u)| ] = H[u] + E_u[ sum_j log(1 - tanh(u_j)^2) ]

    i.e. the pre-squash Gaussian entropy minus ``E[-log|det J|]`` (the correction is ≤ 0: squashing
    into ``(-1, 1)`` can only lose entropy). ``H[u]`` is exact; only the Jacobian term is estimated,
    with ``n_samples`` reparameterised draws ``u = mean + σ ε`` per state.

    Why a fixed sample set: d_PEG differences entropies of consecutive cycles, so Monte-Carlo noise
    would masquerade as an entropy change. All draws ``ε`` come from ``rng``; a caller that seeds a
    fresh generator with the same seed every cycle (the monitor does) uses the *same* ``ε`` each
    time (common random numbers), so the estimate is a deterministic, smooth function of
    ``(mean, log_std)`` and cycle-to-cycle differences reflect the policy only.

    Returns one entropy per state, shape ``[N]`` for ``[N, act_dim]`` inputs.
    """
    if n_samples < 1:
        raise ValueError(f"n_samples must be >= 1, got {n_samples}")
    mu = _as_f64(mean)
    ls = _as_f64(log_std)
    mu, ls = np.broadcast_arrays(mu, ls)
    eps = rng.standard_normal((n_samples, *mu.shape))
    u = mu[None, ...] + np.exp(ls)[None, ...] * eps
    log_det = np.sum(log_one_minus_tanh_sq(u), axis=-1).mean(axis=0)
    return diag_gaussian_entropy(ls) + log_det


def d_peg(entropy_now: float, entropy_prev: float, delta_t: float) -> float:
    """Policy-entropy gradient: ``(H_k - H_{k-1}) / ΔT`` (mean entropies over the evaluation states).

    Persistently large negative values signal premature entropy collapse.
    """
    if delta_t <= 0:
        raise ValueError(f"delta_t must be > 0, got {delta_t}")
    return (float(entropy_now) - float(entropy_prev)) / float(delta_t)


# --------------------------------------------------------------------------------------------------
# Temporal policy divergence
# --------------------------------------------------------------------------------------------------


def sym_kl_diag_gaussians(mu1: ArrayLike, logstd1: ArrayLike, mu2: ArrayLike, logstd2: ArrayLike) -> float:
    """``½ E_s[KL(π1||π2) + KL(π2||π1)]`` for diagonal Gaussians, averaged over the states (rows).

    Closed form per state: the log-ratio terms cancel and what remains is
    ``¼ sum_j [(σ1² + Δμ²)/σ2² + (σ2² + Δμ²)/σ1² - 2]``.

    For SAC's tanh-squashed Gaussians pass the *pre-squash* parameters: KL divergence is invariant
    under any bijection applied to both distributions, and both policies share the same ``tanh``,
    so the KL of the pre-squash Gaussians *is* the KL of the squashed policies — exactly, without
    sampling.
    """
    m1, l1, m2, l2 = (_as_f64(x) for x in (mu1, logstd1, mu2, logstd2))
    var1 = np.exp(2.0 * l1)
    var2 = np.exp(2.0 * l2)
    dm2 = (m1 - m2) ** 2
    per_state = 0.25 * np.sum((var1 + dm2) / var2 + (var2 + dm2) / var1 - 2.0, axis=-1)
    return float(np.mean(per_state))


def d_tpd(mean_now: ArrayLike, logstd_now: ArrayLike, mean_prev: ArrayLike, logstd_prev: ArrayLike) -> float:
    """Temporal policy divergence between the previous and the current policy snapshot.

    Both policies must be evaluated on the *same* states (the current cycle's evaluation states),
    so the divergence measures a change of policy, not a change of state distribution.
    """
    return sym_kl_diag_gaussians(mean_prev, logstd_prev, mean_now, logstd_now)


# --------------------------------------------------------------------------------------------------
# Potential–value correlation
# --------------------------------------------------------------------------------------------------


def pearson(x: ArrayLike, y: ArrayLike, eps: float = 1e-8) -> float:
    """Regularised Pearson correlation, eq. (16): ``Cov(x,y) / (sqrt(Var x + ε) sqrt(Var y + ε))``.

    Population (1/N) moments are used throughout. ``ε`` keeps the value finite — and near 0 rather
    than undefined — when either series is constant (e.g. a freshly re-initialised potential).
    """
    xa = _as_f64(x).ravel()
    ya = _as_f64(y).ravel()
    if xa.shape != ya.shape:
        raise ValueError(f"pearson needs equal lengths, got {xa.shape} and {ya.shape}")
    if xa.size == 0:
        return 0.0
    xc = xa - xa.mean()
    yc = ya - ya.mean()
    cov = float(np.mean(xc * yc))
    return cov / (float(np.sqrt(np.mean(xc * xc) + eps)) * float(np.sqrt(np.mean(yc * yc) + eps)))


def d_pvc(phi: ArrayLike, value: ArrayLike, eps: float = PVC_EPS) -> float:
    """Potential–value correlation on the fixed evaluation set: ``pearson(Φ(s), V̂_ext(s))``."""
    return pearson(phi, value, eps)


# --------------------------------------------------------------------------------------------------
# Factor attentional plasticity
# --------------------------------------------------------------------------------------------------


def _xlogy_ratio(p: FloatArray, m: FloatArray) -> float:
    """``sum p log(p/m)`` with the convention ``0 log 0 = 0`` (``m = 0`` only by subnormal underflow)."""
    mask = (p > 0.0) & (m > 0.0)
    return float(np.sum(p[mask] * np.log(p[mask] / m[mask])))


def jsd(p: ArrayLike, q: ArrayLike) -> float:
    """Jensen–Shannon divergence in nats, bounded by ``ln 2``.

    Inputs are non-negative weights; each is renormalised to sum to one first (so attention means
    restricted to a subset of factors can be passed directly). An all-zero input is treated as the
    uniform distribution.
    """
    pa = _as_f64(p).ravel()
    qa = _as_f64(q).ravel()
    if pa.shape != qa.shape:
        raise ValueError(f"jsd needs equal lengths, got {pa.shape} and {qa.shape}")
    if pa.size == 0:
        return 0.0
    if np.any(pa < 0) or np.any(qa < 0):
        raise ValueError("jsd needs non-negative weights")
    pa = pa / pa.sum() if pa.sum() > 0 else np.full_like(pa, 1.0 / pa.size)
    qa = qa / qa.sum() if qa.sum() > 0 else np.full_like(qa, 1.0 / qa.size)
    m = 0.5 * (pa + qa)
    value = 0.5 * _xlogy_ratio(pa, m) + 0.5 * _xlogy_ratio(qa, m)
    return float(min(max(value, 0.0), _LOG2))


def d_fap(mean_attn_prev: Mapping[str, float], mean_attn_now: Mapping[str, float]) -> float:
    """Factor attentional plasticity: JSD between mean attentions restricted to the shared factor IDs.

    Only names present in both cycles are compared (the outer loop may add or prune factors), and
    each restricted vector is renormalised. With fewer than two shared factors there is no
    distribution to compare and the plasticity is reported as 0.
    """
    shared = sorted(set(mean_attn_prev) & set(mean_attn_now))
    if len(shared) < 2:
        return 0.0
    p = np.array([mean_attn_prev[k] for k in shared], dtype=np.float64)
    q = np.array([mean_attn_now[k] for k in shared], dtype=np.float64)
    return jsd(p, q)


# --------------------------------------------------------------------------------------------------
# Normalised residual prediction error
# --------------------------------------------------------------------------------------------------


def d_rpe(
    phi_s: ArrayLike,
    r_ext: ArrayLike,
    phi_next: ArrayLike,
    gamma: float,
    terminal_mask: ArrayLike | None = None,
    eps: float = RPE_EPS,
) -> float:
    """Normalised residual prediction error, eq. (18).

    ``E[(Φ(s_t) - y_t)^2] / (Var[y_t] + ε)`` with ``y_t = r_ext + γ Φ(s_{t+1})``. At a true
    (absorbing) terminal the bootstrap is dropped, ``y_t = r_ext``, matching the alignment loss's
    treatment of ``Φ(s_T)``; time-limit truncations must *not* be marked terminal. Being a ratio,
    the value is scale-free: ~1 means Φ explains no more than a constant predictor would.
    """
    ps = _as_f64(phi_s).ravel()
    r = _as_f64(r_ext).ravel()
    pn = _as_f64(phi_next).ravel()
    if not (ps.shape == r.shape == pn.shape):
        raise ValueError("d_rpe inputs must have equal lengths")
    if ps.size == 0:
        return 0.0
    cont = np.ones_like(ps) if terminal_mask is None else 1.0 - _as_f64(terminal_mask).ravel()
    target = r + gamma * cont * pn
    return float(np.mean((ps - target) ** 2) / (np.var(target) + eps))
