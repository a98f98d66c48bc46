"""From diagnostic evidence to edit hypotheses (section 4.4.2).

Two parts. The *rules* map the anomalous components of the diagnostic vector to the operators they
call for (low PVC → Gate/Refactor; high RPE with poor return → Add, backing off to Scale/Sat; near-zero
FAP → Gate/Prune; large TPD → Sat). The *linear surrogate* predicts how an edit moves the
(standardised) diagnostics, ``Δd ≈ J_F · ΔF``, where ΔF counts the operators an edit applies and J_F is
a finite-difference Jacobian estimated from this run's own accepted edits — before there are any, a
documented library prior. Candidates are scored by
``score(o) = ⟨w, sign(∇) ⊙ Δd̂(o)⟩ − λ_comp · Comp(o)``, where ∇ is the KDE gradient (the direction
towards the healthy manifold), w prioritises PVC and RPE, and Comp penalises complexity.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mira.engineer.srr_prompt import Hypothesis

METRICS = ("peg", "tpd", "pvc", "fap", "rpe")
OPERATORS = ("Scale", "Sat", "Gate", "Refactor", "Add", "Prune")

# Library prior for J_F: expected change of each standardised diagnostic (rows, METRICS order) when one
# operator (columns, OPERATORS order) is applied. Signs encode the section 4.4.2 rules: gating or
# refactoring a proxy recouples the potential to the return (PVC up) and lowers the residual; adding a
# missing factor lowers the residual plateau and revives exploration (PEG up) and attention (FAP up);
# saturation damps oscillation (TPD down); pruning a dominant factor unfreezes attention.
PRIOR_JF = np.array(
    [
        #  Scale  Sat   Gate  Refac  Add   Prune
        [0.00, 0.00, 0.10, 0.05, 0.50, 0.10],  # peg
        [-0.10, -0.60, -0.10, -0.10, 0.20, 0.00],  # tpd
        [0.10, 0.10, 0.80, 0.60, 0.20, 0.10],  # pvc
        [0.05, 0.05, 0.40, 0.20, 0.30, 0.40],  # fap
        [-0.10, -0.10, -0.30, -0.30, -0.70, 0.10],  # rpe
    ]
)

# Healthy directions used when no KDE gradient is available (the no-MCM ablation): higher entropy
# change, lower oscillation, higher potential-value correlation, livelier attention, lower residual.
DEFAULT_DIRECTION = np.array([1.0, -1.0, 1.0, 1.0, -1.0])

DEFAULT_WEIGHTS = np.array([0.5, 0.5, 1.0, 0.5, 1.0])


def rule_hypotheses(
    d: dict[str, float], return_is_poor: bool, z_low: float = -1.0, z_high: float = 1.0
) -> list[Hypothesis]:
    """The evidence-to-operator rules of section 4.4.2 on a standardised diagnostic vector."""
    out: list[Hypothesis] = []
    if d.get("pvc", 0.0) <= z_low:
        out.append(Hypothesis("Gate", 1.0,
                              "low/negative PVC: potential decoupled from return; gate the proxy on posture"))
        out.append(Hypothesis("Refactor", 0.6, "low PVC: embed physical consistency in the proxy"))
    if d.get("rpe", 0.0) >= z_high and return_is_poor:
        out.append(Hypothesis("Add", 1.0, "high RPE plateau with poor return: the factors miss information"))
        out.append(Hypothesis("Sat", 0.3, "back-off if variance explodes"))
    if abs(d.get("fap", 0.0)) <= 0.1 or d.get("fap", 0.0) <= z_low:
        out.append(Hypothesis("Gate", 0.5, "near-zero FAP: attention ossified; add state dependence"))
        out.append(Hypothesis("Prune", 0.3, "near-zero FAP: an over-dominant factor"))
    if d.get("tpd", 0.0) >= z_high:
        out.append(Hypothesis("Sat", 0.8, "large TPD oscillation without gains: saturate the fastest-varying term"))
    if d.get("peg", 0.0) <= z_low:
        out.append(Hypothesis("Add", 0.6, "entropy collapsing: the policy needs a new incentive to explore"))
    merged: dict[str, Hypothesis] = {}
    for h in out:
        if h.operator not in merged or merged[h.operator].score < h.score:
            merged[h.operator] = h
    return sorted(merged.values(), key=lambda h: -h.score)


@dataclass
class EditSurrogate:
    """The linear surrogate Δd ≈ J_F · ΔF, refined by finite differences from accepted edits."""

    jacobian: np.ndarray = field(default_factory=lambda: PRIOR_JF.copy())
    weights: np.ndarray = field(default_factory=lambda: DEFAULT_WEIGHTS.copy())
    lambda_comp: float = 0.05
    learning_rate: float = 0.5
    """How far one observed edit moves J_F's columns towards its finite-difference estimate."""
    observations: int = 0

    @staticmethod
    def operator_counts(operators: list[str]) -> np.ndarray:
        counts = np.zeros(len(OPERATORS))
        for op in operators:
            if op in OPERATORS:
                counts[OPERATORS.index(op)] += 1
        return counts

    def predict(self, operators: list[str]) -> np.ndarray:
        """Predicted change of the standardised diagnostics, METRICS order."""
        return np.asarray(self.jacobian @ self.operator_counts(operators))

    def score(self, operators: list[str], direction: np.ndarray | None, complexity: float) -> float:
        """``⟨w, sign(∇) ⊙ Δd̂⟩ − λ_comp · Comp`` (J_SRR for a candidate program)."""
        sign = np.sign(DEFAULT_DIRECTION if direction is None or not np.any(direction) else direction)
        return float(np.dot(self.weights, sign * self.predict(operators)) - self.lambda_comp * complexity)

    def observe(self, operators: list[str], d_before: np.ndarray, d_after: np.ndarray) -> None:
        """Finite-difference update from an accepted edit: the observed Δd is spread over the columns of
        the operators it used (least-squares for the counts vector), blended into J_F."""
        counts = self.operator_counts(operators)
        norm = float(counts @ counts)
        if norm == 0:
            return
        delta = np.asarray(d_after, dtype=np.float64) - np.asarray(d_before, dtype=np.float64)
        if not np.all(np.isfinite(delta)):
            return
        residual = delta - self.jacobian @ counts
        self.jacobian += self.learning_rate * np.outer(residual, counts) / norm
        self.observations += 1

    def state_dict(self) -> dict[str, Any]:
        return {"jacobian": self.jacobian.copy(), "weights": self.weights.copy(), "observations": self.observations}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.jacobian = np.asarray(state["jacobian"], dtype=np.float64).copy()
        self.weights = np.asarray(state["weights"], dtype=np.float64).copy()
        self.observations = int(state["observations"])


def complexity(num_edits: int, delta_k: int, code_growth_chars: int) -> float:
    """Comp(o): number of edits, change in factor count, and added code (per 100 characters)."""
    return float(num_edits + abs(delta_k) + max(code_growth_chars, 0) / 100.0)
