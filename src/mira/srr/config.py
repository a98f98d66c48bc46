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
    delta_q: float = 0.5
    """Δq: how much a backoff raises the anomaly percentile (capped at 99)."""
    sandbox_timeout_s: float = 15.0
    """Wall-clock bound of one candidate's sandbox check."""
