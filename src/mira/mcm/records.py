"""Plain data crossing MCM's boundary: the per-cycle input snapshot and the per-cycle result.

The trainer never hands MCM its networks or replay buffer. It evaluates what the monitor needs on
the cycle's held-out states and packs the numbers into a :class:`CycleSnapshot` of NumPy arrays;
MCM answers with an :class:`MCMResult`. This keeps the monitor testable on synthetic data and its
checkpoint independent of any model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

METRIC_NAMES: tuple[str, ...] = ("peg", "tpd", "pvc", "fap", "rpe")
"""Order of the components of the diagnostic vector d (section 4.3.1)."""

# (reading when the healthy direction is UP, i.e. ∇ > 0 and the metric is too low;
#  reading when the healthy direction is DOWN, i.e. ∇ < 0 and the metric is too high)
READINGS: dict[str, tuple[str, str]] = {
    "peg": ("policy entropy collapsing", "policy entropy rising abnormally fast"),
    "tpd": ("policy frozen between snapshots (updates stalled)", "policy oscillating between snapshots"),
    "pvc": ("potential decoupled from return", "potential unusually tightly coupled to return"),
    "fap": ("attention ossified", "attention churning between cycles"),
    "rpe": (
        "residual error unusually low (potential tracks return closely)",
        "potential cannot explain return (informational bottleneck)",
    ),
}


# (metric, sign of ∇ log p) pairs whose deviation is an improvement, not a pathology: the healthy
# density lies toward a lower PVC or a higher RPE only when the current one is better than usual.
IMPROVEMENTS: frozenset[tuple[str, int]] = frozenset({("pvc", -1), ("rpe", 1)})


def is_improvement(metric: str, gradient: float) -> bool:
    """Whether a contributor's deviation reads as an improvement: the monitor logs such an anomaly as benign
    instead of triggering (see :mod:`mira.mcm.monitor`)."""
    return (metric, 1 if gradient > 0 else -1) in IMPROVEMENTS


def reading(metric: str, gradient: float) -> str:
    """One-line human reading of a metric whose healthy direction has sign ``gradient``."""
    up, down = READINGS[metric]
    return up if gradient > 0 else down


@dataclass(kw_only=True)
class CycleSnapshot:
    """Everything MCM needs for one outer cycle, as plain NumPy values computed by the trainer.

    Policy statistics are diagonal-Gaussian ``(mean, log_std)`` rows ``[N, act_dim]`` on the cycle's
    held-out evaluation states: for SAC the pre-squash parameters (``squashed=True``), for DDPG the
    Gaussian surrogate of ``DDPG.policy_stats`` (``squashed=False``).
    """

    step: int
    """Environment step at the end of the cycle."""

    policy_mean: FloatArray
    """Current policy's Gaussian mean on the evaluation states, ``[N, act_dim]``."""

    policy_log_std: FloatArray
    """Current policy's Gaussian log std on the same states, ``[N, act_dim]``."""

    squashed: bool
    """True for a tanh-squashed Gaussian (SAC): entropy then gets the tanh-Jacobian correction."""

    prev_policy_mean: FloatArray | None = None
    """The PREVIOUS snapshot's policy mean on the SAME states (None on the first cycle)."""

    prev_policy_log_std: FloatArray | None = None
    """The PREVIOUS snapshot's policy log std on the SAME states (None on the first cycle)."""

    entropy: float | None = None
    """Mean policy entropy over the evaluation states; None lets MCM compute it from the stats."""

    phi_eval: FloatArray
    """Potential Φ(s) on the FIXED evaluation state set, ``[M]``."""

    value_eval: FloatArray
    """Extrinsic value estimate V̂_ext(s) on the same fixed set, ``[M]``."""

    attention_mean: dict[str, float]
    """Mean factor-attention weight per factor name over the evaluation states."""

    phi_s: FloatArray
    """Φ(s_t) on the held-out transition batch, ``[B]``."""

    r_ext: FloatArray
    """Extrinsic reward r_t of those transitions, ``[B]``."""

    phi_next: FloatArray
    """Φ(s_{t+1}) of those transitions, ``[B]``."""

    terminal: FloatArray
    """1.0 where s_{t+1} is a true terminal (not a time-limit truncation), else 0.0, ``[B]``."""

    smoothed_return: float
    """Mean extrinsic evaluation return of this cycle (G̅_k, the buffer-gating signal)."""

    factor_ids_changed: bool = False
    """True on the first cycle after an accepted factor-set edit (logged; FAP already compares
    only the shared factor IDs)."""


class Contributor(NamedTuple):
    """One metric-level attribution forwarded to SRR with a trigger."""

    metric: str
    """Metric name (one of ``METRIC_NAMES``)."""
    value: float
    """The metric's standardised, smoothed value in d (the space the gradient lives in)."""
    gradient: float
    """Its component of ``∇ log p_healthy(d)``: the sign is the direction back toward health."""
    reading: str
    """One-line human reading, e.g. "policy entropy collapsing"."""


@dataclass(kw_only=True)
class MCMResult:
    """Outcome of one ``MetacognitiveMonitor.diagnose`` call."""

    step: int
    cycle: int
    """0-based index of the cycle (number of diagnose calls before this one)."""
    metric_names: tuple[str, ...] = METRIC_NAMES
    d_raw: FloatArray
    """Raw diagnostic vector, in ``metric_names`` order."""
    z: FloatArray
    """Robustly standardised vector before EMA smoothing."""
    d: FloatArray
    """Standardised and EMA-smoothed vector: the one scored by the KDE."""
    score: float
    """Anomaly score S = -log p_healthy(d); NaN during warm-up."""
    threshold: float
    """τ_trigger (q-th percentile of the score history); NaN during warm-up."""
    release_threshold: float
    """τ_release = τ_trigger - Δ_hyst; NaN during warm-up."""
    trigger: bool
    in_cooldown: bool
    """True when this cycle's trigger check was suppressed by the cooldown."""
    cooldown_left: int
    """Cooldown counter after this cycle (K_cool right after a trigger)."""
    buffer_fill: int
    warmup: bool
    anomalous: bool
    """Hysteresis state after this cycle: True from a trigger until S < τ_release."""
    above: int
    """u: consecutive cycles with S > τ_trigger, this one included."""
    q: float
    bandwidth: float
    inserted: bool
    """Whether d entered the healthy buffer this cycle."""
    baseline: float
    """Return baseline b_k the cycle's return was compared with (before updating it)."""
    smoothed_return: float
    factor_ids_changed: bool = False
    gradient: dict[str, float] = field(default_factory=dict)
    """∇ log p_healthy(d) by metric; all zeros unless ``trigger`` or ``benign``."""
    contributors: list[Contributor] = field(default_factory=list)
    """Top-m metrics by |∇| on a trigger (or a benign anomaly); empty otherwise."""
    benign: bool = False
    """A persistent anomaly that would have triggered, led by an improvement: no trigger."""

    def as_row(self) -> dict[str, Any]:
        """Flat row for ``diagnostics.csv``; the keys are exactly :func:`row_fields`."""
        row: dict[str, Any] = {"cycle": self.cycle, "step": self.step}
        for i, name in enumerate(self.metric_names):
            row[f"raw_{name}"] = float(self.d_raw[i])
        for i, name in enumerate(self.metric_names):
            row[f"z_{name}"] = float(self.z[i])
        for i, name in enumerate(self.metric_names):
            row[f"d_{name}"] = float(self.d[i])
        for name in self.metric_names:
            row[f"grad_{name}"] = float(self.gradient.get(name, 0.0))
        row.update(
            {
                "score": self.score,
                "threshold": self.threshold,
                "release_threshold": self.release_threshold,
                "q": self.q,
                "above": self.above,
                "trigger": int(self.trigger),
                "benign": int(self.benign),
                "anomalous": int(self.anomalous),
                "in_cooldown": int(self.in_cooldown),
                "cooldown_left": self.cooldown_left,
                "warmup": int(self.warmup),
                "buffer_fill": self.buffer_fill,
                "inserted": int(self.inserted),
                "bandwidth": self.bandwidth,
                "smoothed_return": self.smoothed_return,
                "baseline": self.baseline,
                "factor_ids_changed": int(self.factor_ids_changed),
                "contributors": ";".join(c.metric for c in self.contributors),
            }
        )
        return row

    def evidence(self) -> dict[str, Any]:
        """JSON-ready evidence for SRR: d_raw, d, S, τ, gradient and contributors by name."""

        def _f(x: float) -> float | None:
            return None if math.isnan(x) else float(x)

        return {
            "step": self.step,
            "d_raw": {n: float(v) for n, v in zip(self.metric_names, self.d_raw, strict=True)},
            "d": {n: float(v) for n, v in zip(self.metric_names, self.d, strict=True)},
            "score": _f(self.score),
            "threshold": _f(self.threshold),
            "gradient": dict(self.gradient),
            "contributors": [c._asdict() for c in self.contributors],
        }


def row_fields(metric_names: tuple[str, ...] = METRIC_NAMES) -> list[str]:
    """Column names of :meth:`MCMResult.as_row`, for creating ``diagnostics.csv`` up front."""
    cols = ["cycle", "step"]
    for prefix in ("raw", "z", "d", "grad"):
        cols += [f"{prefix}_{n}" for n in metric_names]
    cols += [
        "score",
        "threshold",
        "release_threshold",
        "q",
        "above",
        "trigger",
        "benign",
        "anomalous",
        "in_cooldown",
        "cooldown_left",
        "warmup",
        "buffer_fill",
        "inserted",
        "bandwidth",
        "smoothed_return",
        "baseline",
        "factor_ids_changed",
        "contributors",
    ]
    return cols
