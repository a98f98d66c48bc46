"""Which of the task's features explain the returns the current program cannot: the evidence for a
structural repair.

The decomposition head fits each stored episode's return as the sum over its steps of a weighted sum of
the program's factors (section 3). A *parametric* flaw (a wrong sign, a wrong scale) is absorbed by
those weights. A *structural* flaw is not: when the program misses what the task pays for (a missing
factor, a non-invertible proxy such as ``|v|``, a gate that pays in the wrong region, a saturation that
flattens the signal where progress happens), no weighting of its factors explains the returns, and a
feature of the task card that the task does pay for explains part of what is left.

So for every card feature, in two shapes (its value, as a progress term is written, and minus its
square, as a penalty is), this measures the out-of-sample R² of the returns when that feature's
per-episode sum joins the program's factors, against the program's own out-of-sample R²: k-fold
cross-validation over the stored episodes, with the head's ridge closed form
(:class:`~mira.rewards.decomposition.EpisodeSumRegression`). Out of sample, so that an extra regressor
only scores by explaining returns it was not fitted to. Only episodic returns are read, never the dense
reward. The monitor triggers a repair on a persistent gain that covers most of what the program leaves
unexplained (its ``share``), the engineer is shown the gains, and SRR verifies a candidate by the same
measure.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mira.rewards.decomposition import EpisodeSumRegression

# When a feature explains the returns, or a program explains them better or worse: one home for the
# thresholds of the outer loop's structural trigger, the offline engineer's Add rule and SRR's checks.
# Gains and losses are in out-of-sample R² of the episodic returns; shares are of ``1 − program R²``.

REPAIR_MIN_GAIN = 0.05
"""Structural trigger: out-of-sample R² a feature must add to the program's for a cycle to count."""
REPAIR_MIN_SHARE = 0.75
"""... and the share of what the program leaves unexplained that gain must cover: a missing factor, a loophole
proxy or a misplaced gate leaves a residual one task feature explains almost entirely; a feature that merely
correlates with a skill the agent is acquiring (a gait angle) explains part of it."""
PROPOSE_MIN_GAIN = 0.02
"""Offline engineer: R² a feature must add to be proposed as a new factor (laxer than the trigger: once SRR
is called, a candidate costs a check, not an intervention)."""
PROPOSE_MIN_SHARE = 0.5
"""... and the share of the unexplained part it must cover (at least half: a correlate explains less)."""
MIN_R2_GAIN = 0.02
"""SRR: a candidate also passes when its R² of the returns exceeds the current program's by this. The AUC
test's value labels come from the current program's decomposition, so they cannot vouch for a program that
expresses what the current one misses; the returns themselves can."""
MAX_R2_LOSS = 0.05
"""SRR: a candidate fails, whatever its proxy test, when its R² falls below the current program's by more
than this: it would express what the task pays for worse, which labels from the current program cannot see."""
MAX_UNEXPLAINED_GROWTH = 1.0
"""... or by more than this multiple of what the current program leaves unexplained, when that is smaller:
a candidate may at most double the unexplained part (else a program with R² 0.99998 would accept one that
leaves hundreds of times as much unexplained as "a loss of 0.01")."""


def cv_r2(sums: np.ndarray, returns: np.ndarray, ridge: float, folds: int = 5, centred: bool = False,
          select: bool = False) -> float:
    """Out-of-sample R² of returns ``[E]`` regressed on per-episode summed features ``[E, D]``: episodes
    are dealt into ``folds`` folds round-robin (so every fold spans the whole run), each fold predicted
    by a fit on the others. NaN with fewer than ``2 · folds`` episodes or returns without variance."""
    n = returns.shape[0]
    var = float(np.var(returns))
    if n < 2 * folds or var <= 0:
        return float("nan")
    fold = np.arange(n) % folds
    sse = 0.0
    for k in range(folds):
        train, test = fold != k, fold == k
        theta = EpisodeSumRegression.of(sums[train], returns[train], np.ones(int(train.sum())), ridge=ridge,
                                        centred=centred, select=select).fit()
        sse += float(np.sum((returns[test] - sums[test] @ theta) ** 2))
    return 1.0 - sse / (n * var)


def residual_share(gain: float, program_r2: float) -> float:
    """``gain`` as a fraction of what the program leaves unexplained, ``1 − program_r2``."""
    return gain / max(1.0 - program_r2, 1e-12)


@dataclass
class FeatureGain:
    """How much better the returns are explained with one card feature added, in one shape."""

    feature: str
    form: str
    r2: float
    """Out-of-sample R² of the program's factors plus this feature."""
    gain: float
    """``r2`` minus the program's own out-of-sample R²."""
    share: float
    """``gain`` over what the program leaves unexplained (1 − its out-of-sample R²): near 1 when the
    feature is what the program misses, a fraction when it only correlates with it (a gait, say, with
    the speed the task pays for)."""


@dataclass
class ReturnAttribution:
    """The program's out-of-sample R² of the returns and every feature's gain, largest first."""

    program_r2: float
    episodes: int
    gains: list[FeatureGain] = field(default_factory=list)
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Each feature's observed range over the stored episodes (the engineer's range hints)."""

    @property
    def best(self) -> FeatureGain | None:
        return self.gains[0] if self.gains else None

    def as_dict(self, top: int = 5) -> dict[str, Any]:
        return {"program_cv_r2": self.program_r2, "episodes": self.episodes,
                "feature_gains": [{"feature": g.feature, "form": g.form, "cv_r2": g.r2, "gain": g.gain,
                                   "share": g.share,
                                   "range": list(self.ranges.get(g.feature, (float("nan"), float("nan"))))}
                                  for g in self.gains[:top]]}


def attribute_returns(program_sums: np.ndarray, returns: np.ndarray, feature_sums: dict[str, dict[str, np.ndarray]],
                      ridge: float, folds: int = 5, ranges: dict[str, tuple[float, float]] | None = None,
                      centred: bool = False, select: bool = False) -> ReturnAttribution:
    """The attribution from the program's per-episode head features ``[E, D]`` (bias included), the returns
    ``[E]`` and each feature's per-episode sums in each form (``feature_sums[name][form]``, ``[E]``)."""
    base = cv_r2(program_sums, returns, ridge, folds, centred=centred, select=select)
    gains = []
    for name, by_form in feature_sums.items():
        for form, col in by_form.items():
            r2 = cv_r2(np.concatenate([program_sums, col[:, None]], axis=1), returns, ridge, folds,
                       centred=centred, select=select)
            if np.isfinite(r2) and np.isfinite(base):
                gains.append(FeatureGain(name, form, r2, r2 - base, residual_share(r2 - base, base)))
    gains.sort(key=lambda g: -g.gain)
    return ReturnAttribution(base, int(returns.shape[0]), gains, dict(ranges or {}))
