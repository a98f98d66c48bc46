"""The paper's evaluation metrics (section 5.1.4) and robust aggregates over seeds.

Definitions, on a run's ``eval.csv`` (rows ``step``, ``return_mean``; ``N`` = the run's step budget):

**Asymptotic performance** — the mean of ``return_mean`` over the rows with ``step > 0.9·N``
("the final 10% of training steps"; the comparison is exact, in rational arithmetic). If no row
falls in that window (evaluations sparser than N/10), the last row alone is used, so the metric is
always defined for a run with at least one evaluation.

**Sample efficiency** — the ``step`` of the first row (in step order) whose ``return_mean`` is at
least the threshold ``τ = A_oracle − 0.5·|A_oracle|``, where ``A_oracle`` is the Dense oracle's
asymptotic performance for the same task and algo (the mean over its seeds). For a positive
oracle this is exactly the paper's "50% of the oracle's asymptotic performance" (τ = 0.5·A_oracle).
For a negative oracle "50% of it" would be a bar *above* the oracle (−100 → −50); we keep the bar
half the oracle's magnitude *below* it instead (−100 → −150), so τ ≤ A_oracle always and "reaching
τ" means getting halfway to the oracle on the same scale. A run that never reaches τ has sample
efficiency ``None`` (printed "—").

**Over seeds** — mean and sample standard deviation (ddof = 1; 0 for a single seed). Sample
efficiency is averaged over the seeds that reached τ, and the count of those seeds is reported.

**IQM** — the interquartile mean: sort the n scores, drop ``floor(n/4)`` from each end and average
the rest (``scipy.stats.trim_mean(x, 0.25)``, the convention of rliable, Agarwal et al. 2021).
Confidence intervals are percentile intervals of a **stratified bootstrap**: each replicate
resamples the runs of every task (stratum) with replacement, keeping each task's run count, and
recomputes the statistic on the pooled replicate; seeded, so a report is reproducible.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from fractions import Fraction

import numpy as np
from numpy.typing import NDArray

FINAL_WINDOW = 0.1
ORACLE_FRACTION = 0.5


def _sorted_rows(steps: Sequence[float], returns: Sequence[float]) -> list[tuple[float, float]]:
    if len(steps) != len(returns):
        raise ValueError(f"steps and returns differ in length ({len(steps)} vs {len(returns)})")
    pairs = zip((float(s) for s in steps), (float(r) for r in returns), strict=True)
    return sorted(pairs, key=lambda p: p[0])


def final_window_mask(steps: Sequence[float], total_steps: int, window: float = FINAL_WINDOW) -> list[bool]:
    """Which rows lie in the final ``window`` of training: ``step > (1 − window)·N``, exactly."""
    cutoff = Fraction(total_steps) * (1 - Fraction(str(window)))
    return [Fraction(str(float(s))) > cutoff for s in steps]


def asymptotic_performance(steps: Sequence[float], returns: Sequence[float], total_steps: int,
                           window: float = FINAL_WINDOW) -> float:
    """Mean evaluation return over the rows with ``step > (1 − window)·total_steps``; if there are
    none, the return of the last row. Raises ``ValueError`` on an empty curve."""
    rows = _sorted_rows(steps, returns)
    if not rows:
        raise ValueError("no evaluation rows")
    mask = final_window_mask([s for s, _ in rows], total_steps, window)
    selected = [r for (_, r), keep in zip(rows, mask, strict=True) if keep] or [rows[-1][1]]
    return float(np.mean(selected))


def oracle_threshold(oracle_asymptotic: float, fraction: float = ORACLE_FRACTION) -> float:
    """τ = A − (1 − fraction)·|A|: ``fraction·A`` for A ≥ 0, and below A (not above it) for A < 0."""
    return float(oracle_asymptotic - (1.0 - fraction) * abs(oracle_asymptotic))


def sample_efficiency(steps: Sequence[float], returns: Sequence[float], threshold: float) -> int | None:
    """First evaluation step whose return is ``>= threshold``; ``None`` if it is never reached."""
    for step, ret in _sorted_rows(steps, returns):
        if ret >= threshold:
            return int(step)
    return None


def mean_std(values: Sequence[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (ddof = 1; 0.0 for one value). NaN, NaN when empty."""
    arr = np.asarray([float(v) for v in values], dtype=np.float64)
    if arr.size == 0:
        return math.nan, math.nan
    std = float(arr.std(ddof=1)) if arr.size > 1 else 0.0
    return float(arr.mean()), std


def sample_efficiency_over_seeds(values: Sequence[int | None]) -> tuple[float | None, float | None, int, int]:
    """``(mean, std, reached, seeds)`` over the seeds that reached the threshold; mean/std are None
    when no seed did."""
    reached = [float(v) for v in values if v is not None]
    if not reached:
        return None, None, 0, len(values)
    mean, std = mean_std(reached)
    return mean, std, len(reached), len(values)


def iqm(values: Sequence[float] | NDArray[np.float64]) -> float:
    """Interquartile mean: drop ``floor(n/4)`` scores from each end of the sorted scores, average the
    rest (``scipy.stats.trim_mean(x, 0.25)``)."""
    arr = np.sort(np.asarray(values, dtype=np.float64).ravel())
    if arr.size == 0:
        return math.nan
    cut = int(0.25 * arr.size)
    return float(arr[cut: arr.size - cut].mean())


def _iqm_rows(samples: NDArray[np.float64]) -> NDArray[np.float64]:
    """IQM of every row of a ``[reps, n]`` matrix."""
    n = samples.shape[1]
    cut = int(0.25 * n)
    ordered = np.sort(samples, axis=1)
    return ordered[:, cut: n - cut].mean(axis=1)


def stratified_bootstrap_ci(
    strata: Sequence[Sequence[float]] | Mapping[str, Sequence[float]],
    statistic: Callable[[NDArray[np.float64]], float] | None = None,
    *,
    reps: int = 50_000,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, float]:
    """``(point, low, high)``: the statistic of the pooled scores and its percentile bootstrap CI.

    ``strata`` are the scores of each task (e.g. one score per seed); every replicate draws, for
    each stratum independently, as many scores as it has, with replacement, and computes the
    statistic on the pooled draw. The default statistic is :func:`iqm` (vectorised).
    """
    groups = list(strata.values()) if isinstance(strata, Mapping) else list(strata)
    arrays = [np.asarray(g, dtype=np.float64).ravel() for g in groups]
    arrays = [a for a in arrays if a.size]
    if not arrays:
        return math.nan, math.nan, math.nan
    if reps <= 0 or not 0.0 < confidence < 1.0:
        raise ValueError("reps must be positive and confidence in (0, 1)")
    pooled = np.concatenate(arrays)
    stat = statistic or iqm
    point = float(stat(pooled))
    rng = np.random.default_rng(seed)
    draws = np.concatenate([a[rng.integers(0, a.size, size=(reps, a.size))] for a in arrays], axis=1)
    values = (_iqm_rows(draws) if statistic is None
              else np.array([statistic(row) for row in draws], dtype=np.float64))
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(values, [alpha, 1.0 - alpha])
    return point, float(low), float(high)
