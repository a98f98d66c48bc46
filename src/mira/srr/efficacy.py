"""Proxy efficacy of a candidate program (section 4.4.4), measured offline before acceptance.

States of a fixed evaluation set are labelled by their extrinsic value: the top quantile are
positives, the bottom quantile negatives, the middle is discarded. A candidate's state-only factors
are fed through the *frozen* FAB/VPM to a proxy potential; a useful candidate ranks positives above
negatives. We report the ROC-AUC with a one-sided permutation p-value, and Spearman's ρ between the
proxy potential and the value estimate with its own permutation test, all with a seeded generator so
that a run is reproducible.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy.stats import rankdata


@dataclass
class EfficacyReport:
    auc: float
    auc_p: float
    spearman: float
    spearman_p: float
    n_pos: int
    n_neg: int

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def quantile_labels(values: np.ndarray, lo_q: float = 0.3, hi_q: float = 0.7) -> tuple[np.ndarray, np.ndarray]:
    """Indices of negatives (value ≤ τ_lo) and positives (value ≥ τ_hi); the middle is discarded."""
    values = np.asarray(values, dtype=np.float64)
    tau_lo, tau_hi = np.quantile(values, [lo_q, hi_q])
    neg = np.flatnonzero(values <= tau_lo)
    pos = np.flatnonzero(values >= tau_hi)
    if tau_lo == tau_hi:  # degenerate (constant values): nothing separates the classes
        return np.array([], dtype=np.int64), np.array([], dtype=np.int64)
    return neg, pos


def roc_auc(scores_pos: np.ndarray, scores_neg: np.ndarray) -> float:
    """Area under the ROC curve via the Mann–Whitney statistic (ties count one half)."""
    n_pos, n_neg = len(scores_pos), len(scores_neg)
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    ranks = rankdata(np.concatenate([scores_pos, scores_neg]))
    u = ranks[:n_pos].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u / (n_pos * n_neg))


def _perm_auc_pvalue(scores: np.ndarray, n_pos: int, observed: float, n_perm: int, rng: np.random.Generator) -> float:
    ranks = rankdata(scores)
    n_neg = len(scores) - n_pos
    hits = 0
    for _ in range(n_perm):
        perm = rng.permutation(len(scores))[:n_pos]
        u = ranks[perm].sum() - n_pos * (n_pos + 1) / 2.0
        if u / (n_pos * n_neg) >= observed - 1e-12:
            hits += 1
    return (1 + hits) / (1 + n_perm)


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    rx, ry = rankdata(x), rankdata(y)
    sx, sy = rx.std(), ry.std()
    if sx == 0 or sy == 0:
        return 0.0
    return float(np.mean((rx - rx.mean()) * (ry - ry.mean())) / (sx * sy))


def _perm_spearman_pvalue(
    x: np.ndarray, y: np.ndarray, observed: float, n_perm: int, rng: np.random.Generator
) -> float:
    rx, ry = rankdata(x), rankdata(y)
    rx = (rx - rx.mean()) / (rx.std() + 1e-12)
    ry = (ry - ry.mean()) / (ry.std() + 1e-12)
    hits = 0
    for _ in range(n_perm):
        if float(np.mean(rx[rng.permutation(len(rx))] * ry)) >= observed - 1e-12:
            hits += 1
    return (1 + hits) / (1 + n_perm)


def proxy_efficacy(
    proxy_potential: np.ndarray,
    values: np.ndarray,
    *,
    lo_q: float = 0.3,
    hi_q: float = 0.7,
    n_perm: int = 1000,
    seed: int = 0,
) -> EfficacyReport:
    """AUC of ``proxy_potential`` against value-quantile labels, Spearman ρ, and permutation p-values."""
    phi = np.asarray(proxy_potential, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    if phi.shape != values.shape:
        raise ValueError(f"proxy potential {phi.shape} and values {values.shape} differ in shape")
    rng = np.random.default_rng(seed)
    neg, pos = quantile_labels(values, lo_q, hi_q)
    if len(pos) == 0 or len(neg) == 0 or not np.all(np.isfinite(phi)):
        return EfficacyReport(float("nan"), 1.0, 0.0, 1.0, len(pos), len(neg))
    auc = roc_auc(phi[pos], phi[neg])
    scores = np.concatenate([phi[pos], phi[neg]])
    auc_p = _perm_auc_pvalue(scores, len(pos), auc, n_perm, rng)
    rho = spearman(phi, values)
    rho_p = _perm_spearman_pvalue(phi, values, rho, n_perm, rng)
    return EfficacyReport(auc, auc_p, rho, rho_p, len(pos), len(neg))
