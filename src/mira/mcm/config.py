"""Configuration of the metacognitive monitor.

Table 1 of the paper fixes ``q``, ``N_consecutive``, ``N_B``, ``ΔT`` and ``K_cool``; everything
else is our choice, documented field by field with the reason for its default.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from typing import Any

TABLE1_DELTA_T = 5000
"""Table 1's ΔT: what a monitor used on its own (outside a run, e.g. in a replay) counts a cycle as."""


@dataclass
class MCMConfig:
    """Hyperparameters of MCM (section 4.3, Algorithm 1)."""

    q: float = 95.0
    """Anomaly percentile (Table 1). ``τ_trigger`` is the q-th percentile of the score history.
    Raised by :meth:`MetacognitiveMonitor.on_backoff`, capped at ``q_max``."""

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

    ema_beta: float = 0.3
    """EMA decay ``β`` of the standardised components, ``s_k = β s_{k-1} + (1-β) z_k``. 0.3 keeps
    the smoothing light: a step change reaches 91% of its height by its second cycle, so
    ``N_consecutive = 2`` is met at once, while a one-cycle spike (clipped at ``z_clip``) leaves only
    ``β(1-β)·z_clip`` ≈ 0.84 (about one healthy standard deviation of the smoothed series) in the
    next cycle. In synthetic 5-D streams this gives ~2 false triggers per 300 healthy cycles."""

    window: int = 50
    """Rolling window (cycles) of the median/MAD standardiser. 50 cycles (250k steps at ΔT=5k) is
    long enough that a persistent regime shift stays visible for ~25 cycles before the median
    absorbs it, and short enough to follow training phases."""

    min_history: int = 5
    """Past values a component needs before it is standardised (``z = 0`` before)."""

    mad_floor_abs: float = 1e-8
    """Absolute floor of the robust scale ``1.4826·MAD`` (avoids division by zero)."""

    mad_floor_rel: float = 1e-3
    """Relative floor ``· |median|``: changes below 0.1% of a metric's typical level are noise."""

    z_clip: float = 4.0
    """Clip of standardised values, bounding one absurd value's effect on the EMA and the KDE (a
    4-robust-σ deviation is already far outside the healthy cloud; beyond that only the
    persistence matters)."""

    m_base: int = 10
    """``M_base``: the return baseline is an EMA with span ``M_base`` cycles
    (rate ``2/(M_base+1)``); a cycle is inserted as healthy only if its return beats it."""

    insert_when_anomalous: bool = True
    """Paper behaviour (True): buffer insertion is gated by return only. False additionally
    withholds insertion while the monitor is in the anomalous (post-trigger) state, so a pathology
    that SRR could not fix is not learned as "healthy" just because the return still rises."""

    ignore_improvements: bool = True
    """A persistent anomaly whose top contributor (largest |∇ log p|) reads as an *improvement* — Φ unusually tightly
    coupled to return (PVC high), residual unusually low (RPE low) — raises no trigger; it is logged
    (``benign`` in diagnostics.csv). Algorithm 1 is two-sided, but SRR then steers along ∇ log p back
    toward the healthy density, i.e. toward a *worse* PVC or RPE: it would accept edits that undo the
    improvement. False: the paper's two-sided trigger."""

    hyst_fraction: float = 0.5
    """Hysteresis margin as a fraction of the score spread: ``Δ_hyst = hyst_fraction ·
    (τ_trigger - median(S_hist))``. Scale-free on purpose: S is in nats, but its spread depends
    on D and on the bandwidth, so a fixed number of nats would be "small" for one configuration
    and enormous for another. 0.5 releases halfway between the threshold and the typical score;
    with 0.25 a persistent shift was released (and re-triggered) by ordinary score noise after
    its cooldown in about 1 synthetic stream in 10."""

    bandwidth_ema: float = 0.05
    """Rate ``ρ`` of the bandwidth EMA ``h ← (1-ρ) h + ρ h_median`` (a ~20-cycle time constant)."""

    bandwidth_floor: float = 0.05
    """Lower bound on the KDE bandwidth, in standardised units."""

    score_window: int = 50
    """The threshold τ is the q-th percentile of the last this many scores (0: the whole history).
    The median-heuristic bandwidth shrinks as the healthy buffer grows (h ∝ 1/√(2 log(n+1))), so
    scores drift upward during a run; a percentile over all past scores would then be exceeded far
    more often than 1 − q/100 of the time in a perfectly stationary regime."""

    top_m: int = 2
    """Number of metric-level contributors reported on a trigger (ranked by ``|∇ log p|``)."""

    q_max: float = 99.0
    """Cap on ``q`` under back-off (Algorithm 3, line 24)."""

    gamma: float = 0.99
    """Discount ``γ`` in d_RPE's target ``r + γ Φ(s')``; must equal the trainer's γ (Table 1)."""

    pvc_eps: float = 1e-8
    """``ε`` of eq. (16)."""

    rpe_eps: float = 1e-8
    """``ε`` of eq. (18)."""

    entropy_samples: int = 16
    """Draws per state when the monitor itself estimates a tanh-squashed policy's entropy."""

    entropy_seed: int = 0
    """Seed of the fixed noise for that estimate (the same noise every cycle, see metrics)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.q < 100.0:
            raise ValueError(f"q must be in (0, 100), got {self.q}")
        if self.n_consecutive < 1 or self.buffer_size < 1 or self.k_cool < 0 or self.k_warm < 0:
            raise ValueError("n_consecutive, buffer_size >= 1 and k_cool, k_warm >= 0 are required")
        if self.buffer_min > self.buffer_size:
            raise ValueError("buffer_min cannot exceed buffer_size")
        if not 0.0 <= self.ema_beta < 1.0:
            raise ValueError("ema_beta must be in [0, 1)")
        if self.m_base < 1 or (self.delta_t is not None and self.delta_t < 1):
            raise ValueError("m_base and delta_t must be >= 1")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of every field."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MCMConfig:
        """Build from a dict, ignoring unknown keys (forward compatibility of checkpoints)."""
        names = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in names})
