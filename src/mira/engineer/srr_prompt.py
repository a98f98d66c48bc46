"""The SRR request of Appendix A, built from template files.

The same request goes to every backend: its messages are what an LLM reads, and its ``context`` holds
the same facts as structured data for the offline rule-based engineer (which never parses prose).
Every fact in the context is also written into the messages, so the response cache (keyed by the
messages) can never confuse two different requests.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from importlib import resources
from string import Template
from typing import Any

from mira.factors.program import FactorProgram
from mira.llm.base import LLMRequest
from mira.tasks.card import TaskCard

OPERATOR_DOCS = {
    "Scale": 'Scale: multiply an existing factor by a scalar. params: {"alpha": number}',
    "Sat": 'Sat: clip a factor to [lo, hi] (or saturate it smoothly with tanh). params: {"lo": number, "hi": number}',
    "Gate": ('Gate: multiply a factor by a predicate in [0, 1] (state-only for PHI factors). '
             'params: {"predicate": "the predicate as an expression over s"}'),
    "Refactor": ("Refactor: rewrite a factor as an equivalent but loophole-averse expression. params: {} "
                 "(the new code is the factor's entry in updated_factors)"),
    "Add": ('Add: introduce a new physically meaningful signal. params: {"type": "PHI" | "AUX" | "SHAPE"} '
            "(targets: the new factor's name; its code is in updated_factors)"),
    "Prune": "Prune: remove an ineffective, redundant or detrimental factor. params: {} (targets: the factors removed)",
}
"""Each operator with the shape of its ``params``, as the prompt states them."""

TRIGGERS = {
    "anomaly": ("TRIGGER: the metacognitive monitor. Its anomaly score of the learning dynamics crossed the "
                "threshold for several cycles in a row: the diagnostics below look unlike this run's healthy cycles."),
    "structural": ("TRIGGER: the structural check (not the monitor's anomaly score). Cross-validated over the stored "
                   "episodes, a task feature that the program does not read explains episodic returns that the "
                   "program's factors cannot (RETURNS_THE_PROGRAM_CANNOT_EXPLAIN below): the program misses, or "
                   "misshapes, something the task pays for."),
    "periodic": "TRIGGER: a periodic review; no diagnostic evidence is given.",
    "plateau": ("TRIGGER: the monitor's plateau detector. The held-out return has stopped rising and the evaluation "
                "episodes settle in a narrow band of one state feature (PLATEAU below): the policy is stuck where "
                "the program's reward already explains its returns, so a missing feature is not the problem; a way "
                "out of the band is."),
}
"""Why SRR was called, in the words of the prompt (:attr:`Evidence.cause`)."""

MAX_SHAPE_STEPS = 100.0
"""The largest declared range a SHAPE factor may have, in steps of the run's reward per step: a shaping term
may pay for leaving a state many steps' worth, never so much that the task's own reward stops mattering
(SRR refuses a wider one; the prompt says so)."""

FACTOR_USAGE = (
    "HOW THE FACTORS ARE USED: the environment pays only at the end of an episode. The per-step reward the agent "
    "learns from is r(s, a, s') = sum_i w_i * f_i + b, fitted to the episodes' returns (PHI factors at s', AUX "
    "at (s, a); weights refitted after every episode), so a factor's sign and scale are learned: an edit matters "
    "when it changes which quantities, in which form, the program can express. A SHAPE factor is different: "
    "state-only, never fitted to the returns, its value Psi(s) is a potential that the agent receives as "
    "gamma * Psi(s') - Psi(s) on top of that reward, with the size you write; it changes where the agent looks "
    "first, not what is optimal (potential-based shaping). It must declare a finite range_hint, at most "
    f"{MAX_SHAPE_STEPS:g} times the reward per step wide, and keep its values within it."
)


STAGNATION_TOLERANCE = 0.02
"""A return within this fraction of |baseline| above the moving baseline counts as not improving."""


def return_is_poor(recent: float | None, baseline: float | None) -> bool:
    """The return is not improving on its moving baseline: below it, or on a plateau just above it.

    Section 4.4.2's rules ask for "poor return" before adding incentives; a stagnating run sits a
    hair above its own slowly moving baseline as often as below it, so a strict ``recent <= baseline``
    would miss exactly the plateaus the rule is for. Unknown values count as poor (the monitor fired).
    """
    if recent is None or baseline is None or not (math.isfinite(recent) and math.isfinite(baseline)):
        return True
    return recent <= baseline + STAGNATION_TOLERANCE * abs(baseline)


@dataclass
class Evidence:
    """What the monitor found, in the form SRR passes on."""

    step: int
    d: dict[str, float]
    """Standardised, smoothed diagnostics by metric (peg, tpd, pvc, fap, rpe)."""
    d_raw: dict[str, float]
    score: float | None
    threshold: float | None
    gradient: dict[str, float]
    contributors: list[dict[str, Any]]
    """Top contributors: {metric, value, gradient, reading}."""
    recent_return: float
    baseline_return: float
    stagnation_band: dict[str, Any] | None
    attention: dict[str, float]
    guided: bool = True
    """False in the no-MCM ablation: no diagnostic vector reaches the prompt."""
    decomposition: dict[str, Any] | None = None
    """HARS's return decomposition (section 3's parametric alignment): per-feature weights and shares
    of r̂, the fit's R² and per-step residual (:meth:`DecompositionHead.describe`); None when absent."""
    cause: str = "anomaly"
    """Why SRR was called: ``anomaly`` (the monitor triggered), ``structural`` (the returns show a
    structural flaw, :mod:`mira.outer.repair`) or ``periodic`` (the no-MCM ablation's schedule)."""
    return_attribution: dict[str, Any] | None = None
    """Which task features explain returns the program cannot (:meth:`ReturnAttribution.as_dict`): the
    program's out-of-sample R² of the returns and each feature's gain; None when not measured."""
    plateau: dict[str, Any] | None = None
    """The plateau detector's report (:meth:`mira.mcm.plateau.Plateau.as_dict`, with the per-step size of the
    reward) when it is the cause; None otherwise."""

    @property
    def poor_return(self) -> bool:
        """The return is not improving on its baseline (see :func:`return_is_poor`)."""
        return return_is_poor(self.recent_return, self.baseline_return)

    def as_dict(self) -> dict[str, Any]:
        return dict(vars(self))


@dataclass
class Hypothesis:
    """A preferred operator with the evidence behind it: a rule reading of the diagnostics that the
    request passes on (:func:`mira.srr.hypotheses.rule_hypotheses` makes them)."""

    operator: str
    score: float
    because: str

    def as_dict(self) -> dict[str, Any]:
        return {"operator": self.operator, "score": round(self.score, 4), "because": self.because}


def _template(name: str) -> Template:
    return Template(resources.files("mira.engineer").joinpath("prompts", name).read_text(encoding="utf-8"))


def _factor_block(program: FactorProgram) -> str:
    lines = []
    for f in program.factors:
        code = "\n".join("      " + ln for ln in f.code.rstrip("\n").splitlines())
        lines.append(
            f"  - name: {f.name}\n    type: {f.type}\n    code: |\n{code}\n    doc: \"{f.doc}\"\n"
            f"    units: \"{f.units}\"\n    range_hint: \"{f.range_hint}\""
        )
    return "\n".join(lines)


def _decomposition_lines(ev: Evidence) -> list[str]:
    dec = ev.decomposition
    if not dec or not dec.get("episodes"):
        return []
    weights = {k: round(float(v), 4) for k, v in dec["weights"].items()}
    shares = {k: round(float(v), 3) for k, v in dec["shares"].items()}
    return [
        f"RETURN_DECOMPOSITION (episode returns fitted as sums of per-step w·factor + bias over "
        f"{dec['episodes']} episodes; PHI factors read at {'s′' if dec['phi_at'] == 'next' else dec['phi_at']}):",
        f"  weights: {json.dumps(weights)}",
        f"  share_of_reward: {json.dumps(shares)}",
        f"  r2_of_returns: {float(dec['r2']):.4g}, per_step_residual_rms: {float(dec['per_step_residual_rms']):.4g}",
    ]


def _attribution_lines(ev: Evidence) -> list[str]:
    att = ev.return_attribution
    if not att or not att.get("feature_gains"):
        return []
    lines = [f"RETURNS_THE_PROGRAM_CANNOT_EXPLAIN (out-of-sample R² of the episode returns over {att['episodes']} "
             f"episodes: the program's factors {float(att['program_cv_r2']):.3f}; with one task feature added "
             "(read at s′, as its value or as minus its square):"]
    for g in att["feature_gains"]:
        shape = g["feature"] if g["form"] == "value" else f"-{g['feature']}²"
        lo, hi = g["range"]
        share = "" if g.get("share") is None else f", {float(g['share']):.0%} of what the program leaves unexplained"
        lines.append(f"  - {shape}: R² {float(g['cv_r2']):.3f} ({float(g['gain']):+.3f}{share}), observed range "
                     f"[{lo:.4g}, {hi:.4g}]")
    return lines


def _diagnostics_block(ev: Evidence, hypotheses: list[Hypothesis]) -> str:
    """The evidence, with no empty or inert field: what was not measured is left out, and the rule
    hypotheses (readings of the monitor's diagnostics) only where the monitor triggered."""
    if not ev.guided:
        return "\n".join([
            f"RECENT_RETURN: {ev.recent_return:.4g} (baseline {ev.baseline_return:.4g})",
            *_decomposition_lines(ev),
        ])
    vector = ", ".join(f"{k.upper()}={v:.3f}" for k, v in ev.d.items())
    raw = ", ".join(f"{k.upper()}={v:.4g}" for k, v in ev.d_raw.items())
    lines = [
        "DIAGNOSTICS (learning dynamics this cycle):",
        f"  vector (robust z-scores, EMA-smoothed): [{vector}]",
        f"  raw: [{raw}]",
    ]
    if ev.score is not None and ev.threshold is not None and math.isfinite(ev.score):
        lines.append(f"  anomaly_score: {round(ev.score, 4)} (threshold {round(ev.threshold, 4)})")
    if any(abs(v) > 0 for v in ev.gradient.values()):
        lines.append("  direction_to_healthy (KDE gradient): "
                     + json.dumps({k.upper(): round(v, 4) for k, v in ev.gradient.items()}))
    if ev.contributors:
        lines.append("  top_contributors:")
        for c in ev.contributors:
            lines.append(f"    - name: {str(c['metric']).upper()}\n      value: {c['value']:.3f}\n"
                         f"      comment: \"{c['reading']}\"")
    lines.append(f"  recent_return: {ev.recent_return:.4g} (baseline {ev.baseline_return:.4g})")
    if ev.stagnation_band:
        b = ev.stagnation_band
        lines.append(f"  stagnation_band: {b['feature']} = {b['center']:.4g} ± {b['halfwidth']:.4g}")
    if ev.attention:
        lines.append("  factor_attention: " + json.dumps({k: round(v, 4) for k, v in ev.attention.items()}))
    if hypotheses and ev.cause == "anomaly":
        lines.append("  failure_hypotheses (rule readings of the diagnostics, preferred operators):")
        lines += [f"    - {h.operator}: {h.because}" for h in hypotheses]
    lines += _plateau_lines(ev)
    lines += _decomposition_lines(ev)
    lines += _attribution_lines(ev)
    return "\n".join(lines)


def _plateau_lines(ev: Evidence) -> list[str]:
    p = ev.plateau
    if not p:
        return []
    lo, hi = p["visited"]
    lines = [
        "PLATEAU (held-out return flat, episodes settled in a narrow band):",
        f"  return median of the last cycles {float(p['recent_median']):.4g} against {float(p['previous_median']):.4g} "
        f"before ({float(p['rise']):+.1%})" + ("" if p.get("trend") is None else
                                              f"; least-squares trend over both windows {float(p['trend']):+.1%} "
                                              f"± {float(p['trend_se']):.1%} per window"),
        f"  settled band: {p['feature']} = {float(p['center']):.4g} ± {float(p['halfwidth']):.4g}, where the run has "
        f"visited [{lo:.4g}, {hi:.4g}]" + ("" if p.get("start") is None else
                                           f"; the episodes start at {float(p['start']):.4g}"),
        f"  reward per step at the plateau: about {float(p['reward_per_step']):.4g}",
    ]
    if p.get("d_peg") is not None and p.get("d_rpe") is not None:
        lines.append(f"  d_PEG {float(p['d_peg']):+.3f}, d_RPE {float(p['d_rpe']):+.3f} (standardised)")
    return lines


def _refused_block(refused: list[dict[str, Any]]) -> str:
    """The candidates the last intervention refused and why, so that a model does not repeat them."""
    if not refused:
        return ""
    lines = [f"PREVIOUSLY_REFUSED (your proposals at step {refused[0].get('step')} and why each was refused; do not "
             "repeat them unchanged):"]
    for r in refused:
        what = "+".join(r.get("operators") or []) or "reply"
        on = f" on {', '.join(r['targets'])}" if r.get("targets") else ""
        which = "the reply" if r.get("candidate") is None else f"candidate {r['candidate']}"
        lines.append(f"  - {which} [{what}{on}]: {r.get('reason')}")
    return "\n".join(lines) + "\n"


def posture_feature(card: TaskCard) -> str | None:
    for name in ("pitch", "uprightness", "torso_height"):
        if name in card.feature_names:
            return name
    return None


def build_srr_request(
    card: TaskCard,
    program: FactorProgram,
    evidence: Evidence,
    hypotheses: list[Hypothesis],
    max_candidates: int,
    operators: tuple[str, ...],
    action_dim: int,
    refused: list[dict[str, Any]] | None = None,
) -> LLMRequest:
    state_spec, action_spec = card.spec_text(action_dim)
    user = _template("srr_user.txt").substitute(
        task_description=card.description.replace("\n", " "),
        state_spec="\n".join("  " + ln for ln in state_spec.splitlines()),
        action_spec=action_spec.replace("\n", " "),
        constraints="\n".join(f"  - {c}" for c in card.constraints) or "  - none beyond the instructions",
        version=program.version,
        factors=_factor_block(program),
        trigger=TRIGGERS.get(evidence.cause, TRIGGERS["anomaly"]),
        usage=FACTOR_USAGE,
        diagnostics=_diagnostics_block(evidence, hypotheses),
        refused=_refused_block(refused or []),
        operators="\n".join(f"  - {OPERATOR_DOCS[o]}" for o in operators),
        max_candidates=max_candidates,
    )
    system = _template("srr_system.txt").substitute()
    upper = {k.upper(): v for k, v in evidence.d.items()}
    context: dict[str, Any] = {
        "program": program.to_json(),
        "diagnostics": upper if evidence.guided else {},
        "raw_diagnostics": {k.upper(): v for k, v in evidence.d_raw.items()} if evidence.guided else {},
        "gradient": {k.upper(): v for k, v in evidence.gradient.items()} if evidence.guided else {},
        "anomaly_score": evidence.score,
        "top_contributors": [
            {"name": str(c["metric"]).upper(), "value": c["value"], "comment": c["reading"]}
            for c in evidence.contributors
        ] if evidence.guided else [],
        "return_trend": {"recent_mean": evidence.recent_return, "baseline": evidence.baseline_return},
        "stagnation_band": evidence.stagnation_band if evidence.guided else None,
        "posture_feature": posture_feature(card),
        "max_candidates": max_candidates,
        "allowed_operators": list(operators),
        "guided": evidence.guided,
        "features": [{"name": f.name, "units": f.units, "doc": f.doc} for f in card.features],
        "factor_attention": dict(evidence.attention) if evidence.guided else {},
        "decomposition": evidence.decomposition,
        "return_attribution": evidence.return_attribution if evidence.guided else None,
        "plateau": evidence.plateau if evidence.guided else None,
    }
    return LLMRequest(
        messages=[{"role": "system", "content": system}, {"role": "user", "content": user}],
        purpose="srr",
        temperature=0.0,
        context=context,
    )
