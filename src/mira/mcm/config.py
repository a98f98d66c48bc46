"""Configuration of the metacognitive monitor.

Table 1 of the paper fixes ``q``, ``N_consecutive``, ``N_B``, ``ΔT`` and ``K_cool``; the rest is our
choice, documented field by field with the reason for its default. The monitor's fixed constants (EMA,
window, floors, bandwidth, ...) live beside the code that uses them (``standardize``, ``kde``,
``metrics``, ``monitor``); its discount γ is the agent's.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

TABLE1_DELTA_T = 5000
"""Table 1's ΔT: what a monitor used on its own (outside a run, e.g. in a replay) counts a cycle as."""
TABLE1_GAMMA = 0.99
"""Table 1's γ: the discount of d_RPE's target for a monitor used on its own (a run passes the agent's)."""


@dataclass
class MCMConfig:
    """Hyperparameters of MCM (section 4.3, Algorithm 1)."""

    q: float = 95.0
    """Anomaly percentile (Table 1). ``τ_trigger`` is the q-th percentile of the score history.
    Raised by :meth:`MetacognitiveMonitor.on_backoff`, capped at ``monitor.Q_MAX``."""

    n_consecutive: int = 2
    """Persistence ``N_consecutive`` (Table 1): cycles in a row with ``S > τ_trigger`` to trigger."""

    buffer_size: int = 128
    """Healthy-buffer capacity ``N_B`` (Table 1), FIFO eviction."""

    delta_t: int | None = None
    """Outer-cycle length ``ΔT`` in environment steps. None (the default): one episode of the task
    (``--max-episode-steps``, else the card's ``eval_horizon``), so that warm-up, detection and repair
    fit in a 50k–100k-step run; under Table 1's 5,000 (``--preset paper``) the ten warm-up cycles alone
    take 50k steps. Also used for d_PEG when the step difference between snapshots is unavailable."""

    k_cool: int = 10
    """Cooldown ``K_cool`` in cycles (Table 1), set after a trigger and after an accepted edit."""

    k_warm: int = 10
    """Warm-up ``K_warm``: cycles that only fill the buffer. 10 cycles also lets the rolling
    median/MAD see ``min_history`` values before standardised vectors become informative."""

    buffer_min: int = 16
    """``N_B,min``: minimum buffer fill before scoring. 16 points give a usable median-heuristic
    bandwidth in D = 5 while still being reached within the warm-up."""

    min_scores: int = 20
    """Scores needed in the history before a trigger is allowed (scores are still computed and
    logged). Our addition to Algorithm 1: a q-th percentile of fewer than ``100/(100-q)`` = 20
    values is just the maximum, and "the newest score is the largest so far" happens by chance
    with probability 1/n — without this gate the first scored cycles almost surely false-alarm."""

    min_history: int = 5
    """Past values a component needs before it is standardised (``z = 0`` before)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.q < 100.0:
            raise ValueError(f"q must be in (0, 100), got {self.q}")
        if self.n_consecutive < 1 or self.buffer_size < 1 or self.k_cool < 0 or self.k_warm < 0:
            raise ValueError("n_consecutive, buffer_size >= 1 and k_cool, k_warm >= 0 are required")
        if self.buffer_min > self.buffer_size:
            raise ValueError("buffer_min cannot exceed buffer_size")
        if self.delta_t is not None and self.delta_t < 1:
            raise ValueError("delta_t must be >= 1")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of every field."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MCMConfig:
        """Build from a dict, ignoring unknown keys: a checkpoint may hold fields since removed (``gamma``,
        ``ema_beta``, ...), now constants at the values they had by default, or fields of a newer version."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})
