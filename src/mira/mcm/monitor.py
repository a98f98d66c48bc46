"""The metacognitive monitor: Algorithm 1 (MCM.Diagnose) plus the hooks Algorithm 3 calls.

Per cycle the trainer builds a :class:`CycleSnapshot` and calls :meth:`MetacognitiveMonitor.diagnose`.
The monitor computes the raw diagnostics (remembering what it needs from the previous cycle: step,
mean entropy, mean attention), standardises and smooths them, and runs Algorithm 1:

1. warm-up (``k < K_warm`` or ``|B| < N_B,min``): insert d into the buffer (once the standardiser has
   ``min_history`` values, so that d is informative), log a NaN score, no trigger;
2. ``S = -log p_healthy(d)``; append to the score history; ``τ = percentile(history, q)``;
   bandwidth EMA;
3. insert d into the buffer iff the cycle's return beats the moving baseline (EMA, span M_base);
4. ``u`` = consecutive cycles with ``S > τ``;
5. if the cooldown is running: count it down, no trigger; elif ``u ≥ N_consecutive``: trigger,
   compute ``∇ log p`` and the top-m contributors, start the cooldown (K_cool).

Documented additions: a trigger also needs ``min_scores`` real scores (see ``MCMConfig``); the
hysteresis of section 4.3.2 — after a trigger the monitor stays *anomalous* until
``S < τ_release = τ - Δ_hyst``; no new trigger is raised while anomalous, so one persistent
pathology raises one trigger, not one per cooldown period; vectors from before the standardiser
has ``min_history`` values never enter the healthy buffer; τ is taken over the last
``SCORE_WINDOW`` scores; and an anomaly led by an improvement is logged as benign instead of
triggering (Algorithm 1 is two-sided, but SRR would then steer along ∇ log p back toward the
healthy density, i.e. toward a *worse* PVC or RPE, and accept edits that undo the improvement).

The cooldown is owned here. The trainer must act on ``result.trigger`` alone (Algorithm 3's
"trigger and c_cool = 0" is already folded in) and report the SRR outcome through
:meth:`on_edit_accepted` / :meth:`on_backoff`; it must not count the cooldown down itself.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from mira.mcm import metrics
from mira.mcm.band import stagnation_band
from mira.mcm.config import TABLE1_DELTA_T, TABLE1_GAMMA, MCMConfig
from mira.mcm.kde import HealthyModel, top_contributors
from mira.mcm.records import (
    METRIC_NAMES,
    Contributor,
    CycleSnapshot,
    FloatArray,
    MCMResult,
    is_improvement,
    reading,
    row_fields,
)
from mira.mcm.standardize import RobustStandardizer

__all__ = [
    "METRIC_NAMES",
    "Contributor",
    "CycleSnapshot",
    "MCMConfig",
    "MCMResult",
    "MetacognitiveMonitor",
    "row_fields",
    "stagnation_band",
]

_STATE_VERSION = 1

M_BASE = 10
"""``M_base``: the return baseline is an EMA with span ``M_base`` cycles (rate ``2/(M_base+1)``); a cycle is
inserted as healthy only if its return beats it. Ten cycles follow the return's trend while averaging out
one cycle's evaluation noise."""
HYST_FRACTION = 0.5
"""Hysteresis margin ``Δ_hyst = HYST_FRACTION · (τ_trigger - median(S_hist))``: scale-free, since S is in nats
but its spread depends on D and the bandwidth. 0.5 releases halfway between the threshold and the typical
score; with 0.25 a persistent shift was released (and re-triggered) by ordinary score noise after its cooldown
in about 1 synthetic stream in 10."""
SCORE_WINDOW = 50
"""τ is the q-th percentile of the last this many scores: the median-heuristic bandwidth shrinks as the buffer
grows (h ∝ 1/√(2 log(n+1))), so scores drift upward during a run, and a percentile over all past scores would
be exceeded far more often than 1 − q/100 of the time in a perfectly stationary regime."""
TOP_M = 2
"""Metric-level contributors reported on a trigger (ranked by ``|∇ log p|``): the leading reading and one more."""
Q_MAX = 99.0
"""Cap on ``q`` under back-off (Algorithm 3, line 24): back-offs can never make a trigger impossible (q = 100
would be the largest score itself)."""
ENTROPY_SAMPLES = 16
"""Draws per state when the monitor itself estimates a tanh-squashed policy's entropy (only the tanh
correction is sampled; the Gaussian part is exact)."""
ENTROPY_SEED = 0
"""Seed of the fixed noise of that estimate: the same noise every cycle, so that d_PEG sees the policy's
change, not Monte-Carlo noise (see :func:`metrics.tanh_gaussian_entropy`)."""


def _finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


class MetacognitiveMonitor:
    """Stateful MCM: diagnostics → robust standardisation → KDE score → persistent-anomaly trigger.

    All state is reachable through :meth:`state_dict` (plain Python values only, so it survives
    ``torch.save`` / ``torch.load(weights_only=True)``), and a monitor restored from it continues
    bit-for-bit as the original would have.
    """

    def __init__(self, config: MCMConfig | None = None, gamma: float = TABLE1_GAMMA) -> None:
        """``gamma``: the discount of d_RPE's target ``r + γ Φ(s')``; must equal the agent's γ (a run passes
        it), Table 1's 0.99 for a monitor used on its own."""
        self.config = config if config is not None else MCMConfig()
        self.gamma = float(gamma)
        self._build()

    def _build(self) -> None:
        c = self.config
        d = len(METRIC_NAMES)
        self.q: float = float(c.q)
        self.cycle: int = 0
        self.standardizer = RobustStandardizer(d, min_history=c.min_history)
        self.model = HealthyModel(d, capacity=c.buffer_size)
        self.scores: list[float] = []
        self.above: int = 0
        self.cooldown: int = 0
        self.anomalous: bool = False
        self.baseline: float | None = None
        self.prev_step: int | None = None
        self.prev_entropy: float | None = None
        self.prev_attention: dict[str, float] | None = None

    # ------------------------------------------------------------------------------ diagnostics
    def snapshot_entropy(self, snap: CycleSnapshot) -> float:
        """Mean policy entropy of the snapshot: ``snap.entropy`` if given, else computed.

        Computed as the closed-form Gaussian entropy, or for a squashed policy the tanh-corrected
        estimate with fixed noise (``ENTROPY_SEED``), so it is deterministic across cycles.
        """
        if snap.entropy is not None:
            return float(snap.entropy)
        if snap.squashed:
            rng = np.random.default_rng(ENTROPY_SEED)
            h = metrics.tanh_gaussian_entropy(snap.policy_mean, snap.policy_log_std, ENTROPY_SAMPLES, rng)
        else:
            h = metrics.diag_gaussian_entropy(snap.policy_log_std)
        return float(np.mean(h))

    def raw_metrics(self, snap: CycleSnapshot) -> FloatArray:
        """Raw diagnostic vector ``[PEG, TPD, PVC, FAP, RPE]`` of a snapshot (no state change).

        Components that need a previous cycle (PEG, FAP) or previous-policy statistics (TPD) are
        NaN when those are missing; the standardiser treats NaN as missing (``z = 0``).
        """
        return self._raw_metrics(snap, self.snapshot_entropy(snap))

    def _raw_metrics(self, snap: CycleSnapshot, h_now: float) -> FloatArray:
        c = self.config
        if self.prev_entropy is None or self.prev_step is None:
            peg = math.nan
        else:
            dt = snap.step - self.prev_step
            peg = metrics.d_peg(h_now, self.prev_entropy, dt if dt > 0 else c.delta_t or TABLE1_DELTA_T)
        if snap.prev_policy_mean is None or snap.prev_policy_log_std is None:
            tpd = math.nan
        else:
            tpd = metrics.d_tpd(snap.policy_mean, snap.policy_log_std, snap.prev_policy_mean, snap.prev_policy_log_std)
        pvc = metrics.d_pvc(snap.phi_eval, snap.value_eval, metrics.PVC_EPS)
        fap = math.nan if self.prev_attention is None else metrics.d_fap(self.prev_attention, snap.attention_mean)
        rpe = metrics.d_rpe(snap.phi_s, snap.r_ext, snap.phi_next, self.gamma, snap.terminal, metrics.RPE_EPS)
        return np.array([peg, tpd, pvc, fap, rpe], dtype=np.float64)

    def diagnose(self, snap: CycleSnapshot) -> MCMResult:
        """Run one cycle of Algorithm 1 on a trainer snapshot."""
        h_now = self.snapshot_entropy(snap)
        raw = self._raw_metrics(snap, h_now)
        self.prev_step = int(snap.step)
        self.prev_entropy = h_now
        self.prev_attention = {str(k): float(v) for k, v in snap.attention_mean.items()}
        return self.diagnose_raw(
            raw,
            step=snap.step,
            smoothed_return=snap.smoothed_return,
            factor_ids_changed=snap.factor_ids_changed,
        )

    # ------------------------------------------------------------------------------ Algorithm 1
    def diagnose_raw(
        self,
        d_raw: ArrayLike,
        *,
        step: int,
        smoothed_return: float,
        factor_ids_changed: bool = False,
    ) -> MCMResult:
        """Algorithm 1 from an already computed raw vector (the path :meth:`diagnose` takes too)."""
        c = self.config
        raw = np.asarray(d_raw, dtype=np.float64).reshape(len(METRIC_NAMES)).copy()
        k = self.cycle
        self.cycle += 1
        informative = self.standardizer.ready  # before it, z is all zeros: no evidence about health yet
        z, d = self.standardizer.update(raw)

        g = float(smoothed_return)
        baseline_before = self.baseline
        beats = _finite(g) and baseline_before is not None and g > baseline_before
        if _finite(g):
            alpha = 2.0 / (M_BASE + 1.0)
            self.baseline = g if self.baseline is None else self.baseline + alpha * (g - self.baseline)

        common: dict[str, Any] = {
            "step": int(step),
            "cycle": k,
            "d_raw": raw,
            "z": z,
            "d": d,
            "q": self.q,
            "smoothed_return": g,
            "factor_ids_changed": bool(factor_ids_changed),
            "baseline": math.nan if baseline_before is None else float(baseline_before),
        }
        zero_grad = {n: 0.0 for n in METRIC_NAMES}

        # Lines 2-4: warm-up — buffer filling only. Vectors from before the standardiser has seen
        # `min_history` values are all zeros and would make every later vector look anomalous, so
        # they do not enter the healthy buffer.
        if not informative or len(self.model) < c.buffer_min or k < c.k_warm:
            if informative:
                self.model.insert(d)
            self.scores.append(math.nan)
            return MCMResult(
                **common,
                score=math.nan,
                threshold=math.nan,
                release_threshold=math.nan,
                trigger=False,
                in_cooldown=False,
                cooldown_left=self.cooldown,
                buffer_fill=len(self.model),
                warmup=True,
                anomalous=self.anomalous,
                above=self.above,
                bandwidth=math.nan if self.model.bandwidth is None else self.model.bandwidth,
                inserted=informative,
                gradient=zero_grad,
            )

        # Lines 6-7: score, threshold, bandwidth.
        bandwidth_used = self.model.bandwidth if self.model.bandwidth is not None else self.model.init_bandwidth()
        score = self.model.score(d)
        self.scores.append(score)
        hist = np.array([s for s in self.scores if math.isfinite(s)], dtype=np.float64)
        hist = hist[-SCORE_WINDOW:]
        tau = float(np.percentile(hist, self.q))
        self.model.update_bandwidth()

        # Lines 8-10: performance-gated insertion.
        inserted = beats
        if inserted:
            self.model.insert(d)

        # Line 11 and hysteresis.
        self.above = self.above + 1 if score > tau else 0
        delta_hyst = HYST_FRACTION * max(tau - float(np.median(hist)), 0.0)
        release = tau - delta_hyst
        if self.anomalous and score < release:
            self.anomalous = False

        # Lines 12-19: cooldown, then persistence.
        trigger = benign = False
        in_cooldown = False
        gradient = zero_grad
        contributors: list[Contributor] = []
        if self.cooldown > 0:
            self.cooldown -= 1
            in_cooldown = True
        elif self.above >= c.n_consecutive and not self.anomalous and hist.size >= c.min_scores:
            grad = self.model.grad_log_density(d)
            gradient = {n: float(v) for n, v in zip(METRIC_NAMES, grad, strict=True)}
            contributors = [
                Contributor(METRIC_NAMES[i], float(d[i]), float(grad[i]), reading(METRIC_NAMES[i], grad[i]))
                for i in top_contributors(grad, TOP_M)
            ]
            # The largest pull decides: an improvement there is not a pathology to reframe.
            benign = bool(contributors) and is_improvement(contributors[0].metric, contributors[0].gradient)
            if not benign:
                trigger = True
                self.cooldown = c.k_cool
                self.anomalous = True

        return MCMResult(
            **common,
            score=score,
            threshold=tau,
            release_threshold=release,
            trigger=trigger,
            in_cooldown=in_cooldown,
            cooldown_left=self.cooldown,
            buffer_fill=len(self.model),
            warmup=False,
            anomalous=self.anomalous,
            above=self.above,
            bandwidth=bandwidth_used,
            inserted=inserted,
            gradient=gradient,
            contributors=contributors,
            benign=benign,
        )

    # ------------------------------------------------------------------------------ Algorithm 3 hooks
    def on_edit_accepted(self) -> None:
        """An SRR edit was accepted (Algorithm 3, line 20): start a full cooldown ``K_cool``."""
        self.cooldown = self.config.k_cool

    def on_backoff(self, delta_q: float = 0.5) -> None:
        """SRR abstained with back-off (line 24): ``c ← max(c, ⌊K_cool/2⌋)``, ``q ← min(q + Δq, Q_MAX)``."""
        self.cooldown = max(self.cooldown, self.config.k_cool // 2)
        self.q = min(self.q + float(delta_q), Q_MAX)

    @property
    def buffer_fill(self) -> int:
        """Current number of vectors in the healthy buffer."""
        return len(self.model)

    # ------------------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: config, γ, q, counters, histories, standardiser, buffer, h."""
        return {
            "version": _STATE_VERSION,
            "config": self.config.to_dict(),
            "gamma": self.gamma,
            "q": self.q,
            "cycle": self.cycle,
            "standardizer": self.standardizer.state_dict(),
            "model": self.model.state_dict(),
            "scores": [float(s) for s in self.scores],
            "above": self.above,
            "cooldown": self.cooldown,
            "anomalous": self.anomalous,
            "baseline": self.baseline,
            "prev_step": self.prev_step,
            "prev_entropy": self.prev_entropy,
            "prev_attention": None if self.prev_attention is None else dict(self.prev_attention),
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore a :meth:`state_dict` (its config and γ replace this monitor's, so resuming is exact; a
        checkpoint without γ keeps this monitor's)."""
        version = int(state.get("version", 0))
        if version != _STATE_VERSION:
            raise ValueError(f"unsupported MCM state version {version} (expected {_STATE_VERSION})")
        self.config = MCMConfig.from_dict(dict(state["config"]))
        self.gamma = float(state.get("gamma", self.gamma))
        self._build()
        self.q = float(state["q"])
        self.cycle = int(state["cycle"])
        self.standardizer.load_state_dict(dict(state["standardizer"]))
        self.model.load_state_dict(dict(state["model"]))
        self.scores = [float(s) for s in state["scores"]]
        self.above = int(state["above"])
        self.cooldown = int(state["cooldown"])
        self.anomalous = bool(state["anomalous"])
        self.baseline = None if state["baseline"] is None else float(state["baseline"])
        self.prev_step = None if state["prev_step"] is None else int(state["prev_step"])
        self.prev_entropy = None if state["prev_entropy"] is None else float(state["prev_entropy"])
        pa = state["prev_attention"]
        self.prev_attention = None if pa is None else {str(k): float(v) for k, v in pa.items()}
