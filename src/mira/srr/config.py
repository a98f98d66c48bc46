"""SRR hyperparameters (Table 1); imports nothing so that ``mira.config`` can embed it."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SRRConfig:
    """Reward-editing strictness (Table 1)."""

    max_candidates: int = 3
    """M: candidate revisions asked for per intervention."""
    lambda_comp: float = 0.05
    """λ_comp: complexity penalty in J_SRR."""
    min_auc: float = 0.5
    """Accept only candidates whose proxy potential has ROC-AUC above this."""
    max_p_value: float = 0.05
    """... with a permutation p-value below this."""
    permutations: int = 1000
    """Permutations for the AUC and Spearman tests."""
    label_quantiles: tuple[float, float] = (0.3, 0.7)
    """States at or below the first value quantile are negatives, at or above the second positives."""
    delta_q: float = 0.5
    """Δq: how much a backoff raises the anomaly percentile (capped at 99)."""
    operators: tuple[str, ...] = ("Scale", "Sat", "Gate", "Refactor", "Add", "Prune")
    """Admissible edit operators offered to the LLM."""
    sandbox_timeout_s: float = 15.0
    """Wall-clock bound of one candidate's sandbox check."""
    min_r2_gain: float = 0.02
    """A candidate also passes when it explains the episodic returns better than the current program: its
    out-of-sample R² of the stored returns higher by at least this (:mod:`mira.shaping.attribution`). The
    value labels of the AUC test come from the current program's decomposition, so they cannot vouch for
    a program that expresses what the current one misses; the returns themselves can."""
    max_r2_loss: float = 0.05
    """... and a candidate fails, whatever its proxy test, when its out-of-sample R² of the stored returns
    is below the current program's by more than this: it would express what the task pays for worse,
    and the AUC test, whose labels come from the current program, cannot see that."""
    max_unexplained_growth: float = 1.0
    """... or by more than this multiple of what the current program leaves unexplained (1 − its R²), when
    that is smaller: a program that explains the returns almost exactly (R² 0.99998 once the head's
    ridge is chosen by the evidence) would otherwise accept a candidate that leaves hundreds of times as
    much unexplained as "a loss of 0.01". 1.0: a candidate may at most double the unexplained part."""
