"""SRR for the offline engineer: the evidence-to-operator rules of section 4.4.2, applied by hand.

Given the MCM evidence in ``request.context`` it proposes at most M one-edit candidates in the
Appendix A JSON, ranked by how strongly the evidence supports each rule:

* low/negative PVC (potential decoupled from extrinsic value) → Gate the dominant progress Φ-factor
  on a state-only posture predicate (HalfCheetah: ``v_x · (1 − tanh(α θ²))``, section 5.3.1);
  alternative: Refactor it to a heading-consistent form (``v_x cos θ``);
* a plateau reported by the monitor's plateau detector → Add a bounded SHAPE potential that ramps up
  from just above the band where the episodes settle (it reaches the agent as γΨ(s′) − Ψ(s), sized in
  steps of the plateau's reward: :func:`add_escape_potential`); it outranks every other rule;
* high RPE plateau with poor return → Add a bounded, state-only escape bonus localised at the
  stagnation band (HumanoidStandup: ``σ(α (z − z_stag)) · tanh(β v_z)``, section 5.3.2);
  back-off: Scale the largest-range factor down;
* near-zero FAP (ossified attention) → Gate the dominant factor on a state predicate, or Prune it;
* large TPD oscillation without gains → Sat (clip) the fastest-varying term.

Without diagnostics (``guided`` false: the w/o-MCM ablation) it can only propose generic edits from the
program itself (Sat or Scale of the largest-range factor). Each candidate's ``updated_factors`` is the complete
revised factor set, its code only ``s.<feature>``, arithmetic and ``np.tanh/exp/clip/...``; all deterministic.
"""

from __future__ import annotations

import copy
import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from mira.engineer.factorcode import (
    features_used,
    first_return_expr,
    format_range,
    make_factor,
    normalise_expr,
    num,
    parse_range,
    rewrite_returns,
    squared_features,
)
from mira.engineer.offline_evidence import METRICS, RequestContext, parse_evidence
from mira.llm.base import OFFLINE_ENGINEER_LABEL
from mira.shaping.attribution import PROPOSE_MIN_GAIN, PROPOSE_MIN_SHARE

# Rule thresholds: standardised values are robust z-scores (median/MAD), raw values as in 4.3.1.
UNEXPLAINED_CANDIDATES = 2  # Add candidates from the attribution, best features first
PVC_LOW_Z = -1.0
PVC_LOW_RAW = 0.1
RPE_HIGH_Z = 1.0
RPE_HIGH_RAW = 0.5
FAP_LOW_Z = -1.0
FAP_LOW_RAW = 1e-3
TPD_HIGH_Z = 1.5

GATE_ALPHA_ANGLE = 2.0  # 1 - tanh(2 θ²): 0.54 at 0.5 rad (29°), 0.04 at 1 rad, ~0 when flipped
GATE_ALPHA_UPRIGHT = 4.0  # 0.5 (1 + tanh(4 (u - 0.5))): 0.98 upright, 0.5 at 60° tilt, 0.02 lying
EXPLORE_BETA = 2.0  # tanh(2 v_z): 0.76 when rising at 0.5 m/s
EXPLORE_ALPHA_MAX = 100.0  # keeps exp() finite over any height range a body can span
SCALE_BACKOFF = 0.5
ESCAPE_STEPS = 20.0
"""The escape potential's height in steps of the plateau's reward per step: climbing out of the band pays
about this many steps' reward at once, enough to stand out of the critic's noise, bounded whatever happens."""
ESCAPE_RAMP_SHARE, ESCAPE_CLIMB_SHARE = 0.25, 0.5
"""The ramp's width: the largest of twice the band's half-width, RAMP_SHARE of the range the run visits and
CLIMB_SHARE of the climb from the episodes' start to the band (a policy sitting still visits a narrow range)."""


@dataclass
class RankedEdit:
    """One ranked, single-edit revision the offline engineer proposes (serialised as a reply candidate)."""

    edit: dict[str, Any]
    factors: list[dict[str, Any]]
    strength: float
    order: int

    def to_json(self) -> dict[str, Any]:
        return {"edits": [self.edit], "updated_factors": self.factors}


# --------------------------------------------------------------------------- factor selection


def _phi(ev: RequestContext) -> list[dict[str, Any]]:
    return [f for f in ev.factors if f["type"] == "PHI"]


def _width(f: dict[str, Any]) -> float:
    rng = parse_range(f.get("range_hint"))
    return -1.0 if rng is None else rng[1] - rng[0]


def _magnitude(f: dict[str, Any]) -> float | None:
    rng = parse_range(f.get("range_hint"))
    return None if rng is None else max(abs(rng[0]), abs(rng[1]))


def _is_rate(name: str) -> bool:
    return name.endswith(("_rate", "_dot")) or "vel" in name or "omega" in name


def progress_factor(ev: RequestContext) -> dict[str, Any] | None:
    """The Φ-factor that pays for progress: by name, else by reading a velocity linearly."""
    best: tuple[float, int, dict[str, Any]] | None = None
    for i, f in enumerate(_phi(ev)):
        name = f["name"].lower()
        score = 0.0
        if any(k in name for k in ("vel", "progress", "forward", "speed", "run", "height")):
            score += 2.0
        used = features_used(f["code"])
        squared = set(squared_features(f["code"]))
        if any(_is_rate(u) and u not in squared for u in used):
            score += 1.0
        if any(k in name for k in ("stab", "ctrl", "upright", "explore")):
            score -= 3.0
        if score <= 0:
            continue
        score += ev.attention.get(f["name"], 0.0)
        if best is None or score > best[0]:
            best = (score, i, f)
    return None if best is None else best[2]


def dominant_factor(ev: RequestContext) -> dict[str, Any] | None:
    """The Φ-factor the potential leans on: most attention, else progress, else widest range."""
    phi = _phi(ev)
    if not phi:
        return None
    if ev.attention:
        return max(phi, key=lambda f: ev.attention.get(f["name"], -math.inf))
    return progress_factor(ev) or max(phi, key=_width)


def fastest_factor(ev: RequestContext) -> dict[str, Any] | None:
    """The Φ-factor that varies fastest: most (squared) rates read, ties to the widest range."""
    phi = _phi(ev)
    if not phi:
        return None

    def key(f: dict[str, Any]) -> tuple[float, float]:
        squared = set(squared_features(f["code"]))
        score = sum((2.0 if u in squared else 1.0) for u in features_used(f["code"]) if _is_rate(u))
        return score, _width(f)

    return max(phi, key=key)


def widest_factors(ev: RequestContext) -> list[dict[str, Any]]:
    """Φ-factors by decreasing range-hint width (stable for ties)."""
    return sorted(_phi(ev), key=lambda f: -_width(f))


def posture_feature(ev: RequestContext) -> str | None:
    if ev.posture is not None:
        return ev.posture
    for name in ("pitch", "uprightness"):
        if name in ev.feature_names:
            return name
    return None


def _posture_gate(feature: str) -> tuple[str, float]:
    """A state predicate g(s) in (0, 1] that is ~1 in a healthy posture."""
    if "upright" in feature:
        return f"0.5 * (1.0 + np.tanh({num(GATE_ALPHA_UPRIGHT)} * (s.{feature} - 0.5)))", GATE_ALPHA_UPRIGHT
    return f"1.0 - np.tanh({num(GATE_ALPHA_ANGLE)} * np.square(s.{feature}))", GATE_ALPHA_ANGLE


def _with(ev: RequestContext, name: str, change: Callable[[dict[str, Any]], dict[str, Any] | None]) -> list[dict]:
    """The factor set with ``name`` replaced by ``change(factor)`` (dropped when it returns None)."""
    out: list[dict[str, Any]] = []
    for f in ev.factors:
        if f["name"] == name:
            new = change(copy.deepcopy(f))
            if new is not None:
                out.append(new)
        else:
            out.append(copy.deepcopy(f))
    return out


def _fresh_name(ev: RequestContext, base: str) -> str:
    taken = {f["name"] for f in ev.factors}
    if base not in taken:
        return base
    i = 1
    while f"{base}_{i}" in taken:
        i += 1
    return f"{base}_{i}"


def _edit(op: str, targets: list[str], params: dict[str, Any], why: str) -> dict[str, Any]:
    return {"operator": op, "targets": targets, "params": params, "justification": why}


# --------------------------------------------------------------------------- operators


def gate_on_posture(ev: RequestContext, target: dict[str, Any], why: str) -> tuple[dict, list[dict]] | None:
    feature = posture_feature(ev)
    if feature is None or feature in features_used(target["code"]):
        return None
    gate, alpha = _posture_gate(feature)

    def change(f: dict[str, Any]) -> dict[str, Any]:
        f["code"] = rewrite_returns(f["code"], lambda x: f"({x}) * ({gate})")
        f["doc"] = f"{f.get('doc', '')} (gated on posture: pays only while {feature} is healthy)".strip()
        return f

    params = {"gate_code": normalise_expr(gate), "alpha": alpha, "posture_feature": feature}
    return _edit("Gate", [target["name"]], params, why), _with(ev, target["name"], change)


def refactor_heading(ev: RequestContext, target: dict[str, Any], why: str) -> tuple[dict, list[dict]] | None:
    feature = posture_feature(ev)
    if feature is None or feature in features_used(target["code"]):
        return None
    factor = f"s.{feature}" if "upright" in feature else f"np.cos(s.{feature})"

    def change(f: dict[str, Any]) -> dict[str, Any]:
        f["code"] = rewrite_returns(f["code"], lambda x: f"({x}) * {factor}")
        f["doc"] = f"{f.get('doc', '')} (projected on the torso heading via {feature})".strip()
        return f

    factors = _with(ev, target["name"], change)
    new = next(f for f in factors if f["name"] == target["name"])
    params = {"expression": first_return_expr(new["code"]), "posture_feature": feature}
    return _edit("Refactor", [target["name"]], params, why), factors


def saturate(ev: RequestContext, target: dict[str, Any], why: str) -> tuple[dict, list[dict]]:
    rng = parse_range(target.get("range_hint"))
    if rng is None:
        lo, hi = -5.0, 5.0
    else:
        bound = max(abs(rng[0]), abs(rng[1])) / 2.0
        lo, hi = max(rng[0], -bound), min(rng[1], bound)
        if hi <= lo:
            lo, hi = rng
    lo_s, hi_s = num(lo), num(hi)

    def change(f: dict[str, Any]) -> dict[str, Any]:
        f["code"] = rewrite_returns(f["code"], lambda x: f"np.clip({x}, {lo_s}, {hi_s})")
        f["range_hint"] = format_range(lo, hi)
        return f

    params = {"lower": float(lo_s), "upper": float(hi_s)}
    return _edit("Sat", [target["name"]], params, why), _with(ev, target["name"], change)


def scale(ev: RequestContext, target: dict[str, Any], alpha: float, why: str) -> tuple[dict, list[dict]]:
    def change(f: dict[str, Any]) -> dict[str, Any]:
        f["code"] = rewrite_returns(f["code"], lambda x: f"{num(alpha)} * ({x})")
        rng = parse_range(f.get("range_hint"))
        if rng is not None:
            f["range_hint"] = format_range(*sorted((alpha * rng[0], alpha * rng[1])))
        return f

    return _edit("Scale", [target["name"]], {"alpha": alpha}, why), _with(ev, target["name"], change)


def prune(ev: RequestContext, target: dict[str, Any], why: str) -> tuple[dict, list[dict]] | None:
    if target["type"] == "PHI" and len(_phi(ev)) < 2:
        return None
    return _edit("Prune", [target["name"]], {}, why), _with(ev, target["name"], lambda f: None)


def _phi_scale(ev: RequestContext) -> float:
    """Typical magnitude of the Φ-factors (the lower median of range-hint bounds), for commensurate additions.

    The lower median, so that with two factors an addition is sized by the smaller one, never drowning
    the progress term it is meant to help.
    """
    mags = sorted(m for m in (_magnitude(f) for f in _phi(ev)) if m is not None and m > 0)
    if not mags:
        return 1.0
    mid = mags[(len(mags) - 1) // 2]
    return float(f"{min(max(mid, 0.1), 10.0):.2g}")


def _vertical_velocity(ev: RequestContext) -> str | None:
    for name in ("z_velocity", "vz", "v_z", "z_vel", "vertical_velocity"):
        if name in ev.feature_names:
            return name
    return None


def add_escape_bonus(ev: RequestContext, why: str) -> tuple[dict, list[dict]] | None:
    """Section 5.3.2: σ(α (z − z_stag)) · tanh(β v_z), localised at the stagnation band."""
    if ev.band is None:
        return add_bridge(ev, why)
    feature = str(ev.band["feature"])
    center, half = float(ev.band["center"]), max(float(ev.band["halfwidth"]), 0.02)
    alpha = float(num(min(2.0 / half, EXPLORE_ALPHA_MAX)))
    vz = _vertical_velocity(ev)
    size = _phi_scale(ev)
    sigmoid = f"1.0 / (1.0 + np.exp(-{num(alpha)} * (s.{feature} - {num(center)})))"
    drive = f"np.tanh({num(EXPLORE_BETA)} * s.{vz})" if vz is not None else "1.0"
    expr = f"({sigmoid}) * {drive}"
    if size != 1.0:
        expr = f"{num(size)} * ({expr})"
    name = _fresh_name(ev, "r_explore")
    new = make_factor(
        name,
        "PHI",
        expr,
        doc=(
            f"escape bonus localised at the stagnation band {feature} = {num(center)} ± {num(half)}: "
            + (
                "rewards rising (vertical velocity) once at or above the band"
                if vz is not None
                else "rewards being at or above the band"
            )
        ),
        units="1",
        range_hint=format_range(-size if vz is not None else 0.0, size),
    )
    params = {
        "new_factor": name,
        "type": "PHI",
        "feature": feature,
        "z_stag": center,
        "halfwidth": half,
        "alpha": alpha,
        "beta": EXPLORE_BETA if vz is not None else None,
        "velocity_feature": vz,
        "scale": size,
        "code": new["code"],
    }
    return _edit("Add", [name], params, why), [*copy.deepcopy(ev.factors), new]


def add_escape_potential(ev: RequestContext, steps: float = ESCAPE_STEPS) -> tuple[dict, list[dict]] | None:
    """A SHAPE factor Ψ(s) = β · σ((z − c) / w), written with tanh, centred at c = center + w above the band the
    episodes settle in (where Ψ is already 0.27β), rising over a ramp of width w (:data:`ESCAPE_RAMP_SHARE`) to β."""
    if (p := ev.plateau) is None:
        return None
    feature, (lo, hi) = str(p["feature"]), p["visited"]
    climb = 0.0 if p.get("start") is None else abs(float(p["center"]) - float(p["start"]))
    width = max(2.0 * float(p["halfwidth"]), ESCAPE_RAMP_SHARE * (hi - lo), ESCAPE_CLIMB_SHARE * climb, 1e-3)
    center, beta = float(p["center"]) + width, steps * max(abs(float(p["reward_per_step"])), 1e-6)
    expr = f"{num(beta / 2.0)} * (1.0 + np.tanh((s.{feature} - {num(center)}) / {num(2.0 * width)}))"
    band = f"{feature} = {num(float(p['center']))} ± {num(float(p['halfwidth']))}"
    name = _fresh_name(ev, "psi_escape")
    new = make_factor(name, "SHAPE", expr, units="1", range_hint=format_range(0.0, beta),
                      doc=f"escape potential above the band {band} where the policy settles: a ramp of width "
                      f"{num(width)} up to {num(beta)} ({steps:g} steps of the plateau's reward)")
    why = (f"plateau: the held-out return is flat and the episodes settle at {band}; a bounded potential above "
           "the band turns it into a ramp (shaping outside the fitted reward, so it keeps its size)")
    params = {"new_factor": name, "type": "SHAPE", "feature": feature, "ramp_center": center, "ramp_width": width,
              "height": beta, "code": new["code"]}
    return _edit("Add", [name], params, why), [*copy.deepcopy(ev.factors), new]


def add_bridge(ev: RequestContext, why: str) -> tuple[dict, list[dict]] | None:
    """Without a localised band: a bounded, state-only bridge on rising (or forward) motion."""
    size = _phi_scale(ev)
    vz = _vertical_velocity(ev)
    if vz is not None and any("height" in n for n in ev.feature_names):
        feat, doc = vz, "bounded bonus for rising (vertical velocity): a sparse-to-dense bridge"
    elif "x_velocity" in ev.feature_names:
        feat, doc = "x_velocity", "bounded bonus for forward motion: a sparse-to-dense bridge"
    else:
        return None
    name = _fresh_name(ev, "r_bridge")
    expr = f"np.tanh({num(EXPLORE_BETA)} * s.{feat})"
    if size != 1.0:
        expr = f"{num(size)} * {expr}"
    new = make_factor(name, "PHI", expr, doc=doc, units="1", range_hint=format_range(-size, size))
    params = {
        "new_factor": name,
        "type": "PHI",
        "feature": feat,
        "beta": EXPLORE_BETA,
        "scale": size,
        "code": new["code"],
    }
    return _edit("Add", [name], params, why), [*copy.deepcopy(ev.factors), new]


# --------------------------------------------------------------------------- rules


def _fmt(ev: RequestContext, metric: str) -> str:
    parts = []
    if metric in ev.z:
        parts.append(f"standardised {ev.z[metric]:+.2f}")
    if metric in ev.raw:
        parts.append(f"raw {ev.raw[metric]:+.3g}")
    if metric in ev.grad:
        parts.append(f"KDE gradient {ev.grad[metric]:+.2f}")
    return f"d_{metric} " + (", ".join(parts) if parts else "(no value given)")


def _strengths(ev: RequestContext) -> dict[str, float]:
    """How strongly each rule's trigger holds (0 = not at all)."""
    z, raw, g = ev.z, ev.raw, ev.grad
    out: dict[str, float] = {}
    pvc_low = z.get("PVC", 0.0) <= PVC_LOW_Z or raw.get("PVC", 1.0) <= PVC_LOW_RAW
    if pvc_low:
        out["PVC"] = 1.0 + max(-z.get("PVC", 0.0), 0.0) + max(g.get("PVC", 0.0), 0.0)
    rpe_high = z.get("RPE", 0.0) >= RPE_HIGH_Z or raw.get("RPE", 0.0) >= RPE_HIGH_RAW
    if rpe_high and ev.poor_return:
        out["RPE"] = (
            1.0
            + max(z.get("RPE", 0.0), 0.0)
            + max(-g.get("RPE", 0.0), 0.0)
            + 0.5 * max(-z.get("PEG", 0.0), 0.0)
            + (1.0 if ev.band is not None else 0.0)
        )
    fap_low = z.get("FAP", 0.0) <= FAP_LOW_Z or raw.get("FAP", 1.0) <= FAP_LOW_RAW
    if fap_low:
        out["FAP"] = 1.0 + max(-z.get("FAP", 0.0), 0.0) + max(g.get("FAP", 0.0), 0.0)
    if z.get("TPD", 0.0) >= TPD_HIGH_Z and ev.poor_return:
        out["TPD"] = 1.0 + max(z.get("TPD", 0.0), 0.0) + max(-g.get("TPD", 0.0), 0.0)
    if not out:
        # MCM fired but no rule's threshold is met: follow the largest pull of the evidence, among
        # the rules whose preconditions hold (Add and Sat only when the return is not improving).
        pulls = {m: abs(g.get(m, 0.0)) + abs(z.get(m, 0.0)) for m in METRICS}
        eligible = [m for m in METRICS if pulls[m] > 0 and (ev.poor_return or m in ("PVC", "FAP"))]
        if eligible:
            top = max(eligible, key=lambda m: pulls[m])
            out["RPE" if top == "PEG" else top] = 0.5
    return out


def _rule_candidates(ev: RequestContext, metric: str) -> list[tuple[dict, list[dict]] | None]:
    """Primary then alternative proposals for one rule."""
    if metric == "PVC":
        target = progress_factor(ev) or dominant_factor(ev)
        if target is None:
            return []
        why = (
            f"{_fmt(ev, 'PVC')}: potential decoupled from extrinsic value (reward hacking); "
            f"make {target['name']} conditional on a state-only posture predicate (4.4.2: low PVC -> Gate)"
        )
        alt = (
            f"{_fmt(ev, 'PVC')}: embed physical consistency in {target['name']} by aligning it "
            "with the torso heading (4.4.2: low PVC -> Refactor)"
        )
        return [gate_on_posture(ev, target, why), refactor_heading(ev, target, alt)]
    if metric == "RPE":
        trend = (
            ""
            if ev.recent_mean is None or ev.baseline is None
            else f", return {ev.recent_mean:.6g} <= baseline {ev.baseline:.6g}"
        )
        band = (
            ""
            if ev.band is None
            else f"; stagnation localised at {ev.band['feature']} = {float(ev.band['center']):.3g} "
            f"± {float(ev.band['halfwidth']):.3g}"
        )
        why = (
            f"{_fmt(ev, 'RPE')}{trend}, {_fmt(ev, 'PEG')}: high residual plateau with poor return, the "
            f"factor set lacks an escape incentive{band} (4.4.2: high RPE -> Add)"
        )
        out: list[tuple[dict, list[dict]] | None] = [add_escape_bonus(ev, why)]
        widest = widest_factors(ev)
        if widest:
            out.append(
                scale(
                    ev,
                    widest[0],
                    SCALE_BACKOFF,
                    f"{_fmt(ev, 'RPE')}: back-off if variance explodes: scale down the widest-range "
                    f"factor {widest[0]['name']} (4.4.2: Scale)",
                )
            )
        return out
    if metric == "FAP":
        target = dominant_factor(ev)
        if target is None:
            return []
        why = (
            f"{_fmt(ev, 'FAP')}: attention over factors has ossified; make {target['name']} state-dependent "
            "through a posture predicate (4.4.2: near-zero FAP -> Gate)"
        )
        alt = (
            f"{_fmt(ev, 'FAP')}: {target['name']} dominates the potential's attention; remove it "
            "(4.4.2: near-zero FAP -> Prune)"
        )
        return [gate_on_posture(ev, target, why), prune(ev, target, alt)]
    if metric == "TPD":
        target = fastest_factor(ev)
        if target is None:
            return []
        why = (
            f"{_fmt(ev, 'TPD')}: the policy oscillates without gains; saturate the fastest-varying "
            f"term {target['name']} (4.4.2: large TPD -> Sat)"
        )
        return [saturate(ev, target, why)]
    return []


def add_unexplained(ev: RequestContext) -> list[tuple[dict, list[dict]]]:
    """Structural repair: Add the task features that explain the returns the program cannot.

    The evidence is the decomposition's attribution: with a feature's per-episode sum added to the
    program's factors the out-of-sample R² of the episodic returns rises by ``gain``, which is ``share`` of
    what the program leaves unexplained; a feature must cover at least half of it (a missing factor
    covers nearly all, a correlate such as a gait angle a part; SRR verifies either way). The feature enters
    in the shape that earned the gain (its value, or minus its square), as a PHI factor of its own; the
    decomposition head then finds its weight, so neither its scale nor its sign need be guessed.
    Nothing here depends on the feature's or the program's names.
    """
    out: list[tuple[dict, list[dict]]] = []
    used: set[str] = set()
    for entry in ev.unexplained:
        if entry["gain"] < PROPOSE_MIN_GAIN or entry["feature"] in used:
            continue
        if entry["share"] is not None and entry["share"] < PROPOSE_MIN_SHARE:
            continue  # explains part of the residual only: a correlate of what is missing, not the thing
        feature, form, rng = entry["feature"], entry["form"], entry["range"]
        used.add(feature)
        if form == "value":
            expr, polarity = f"s.{feature}", "reward"
            hint = format_range(*rng) if rng else "[-10, 10]"
        else:
            expr, polarity = f"-1.0 * s.{feature} ** 2", "penalty"
            hint = format_range(-max(rng[0] ** 2, rng[1] ** 2), 0.0) if rng else "[-10, 0]"
        name = _fresh_name(ev, f"r_{feature}" if form == "value" else f"r_{feature}_sq")
        before = "?" if ev.program_r2 is None else f"{ev.program_r2:.3f}"
        after = "?" if entry["cv_r2"] is None else f"{entry['cv_r2']:.3f}"
        share = "" if entry["share"] is None else f", {entry['share']:.0%} of what it leaves unexplained"
        why = (f"the program's factors explain the episodic returns out of sample with R² {before}; with "
               f"{'' if form == 'value' else '-'}{feature}{'' if form == 'value' else '²'} added, {after} "
               f"(+{entry['gain']:.3f}{share}): the program misses what the task pays for (Add)")
        factor = make_factor(name, "PHI", expr, doc=f"task feature {feature} ({form}), added because it explains "
                             "returns the program could not", units="1", range_hint=hint)
        factor["polarity"] = polarity
        params = {"new_factor": name, "type": "PHI", "feature": feature, "form": form, "code": factor["code"]}
        out.append((_edit("Add", [name], params, why), [*copy.deepcopy(ev.factors), factor]))
        if len(out) >= UNEXPLAINED_CANDIDATES:
            break
    return out


def _generic(ev: RequestContext) -> list[tuple[dict, list[dict]] | None]:
    """Unguided edits (no diagnostics): tame the largest-range Φ-factors."""
    widest = widest_factors(ev)
    out: list[tuple[dict, list[dict]] | None] = []
    note = "no diagnostic evidence (unguided SRR)"
    if widest:
        out.append(saturate(ev, widest[0], f"{note}: clip the largest-range factor {widest[0]['name']}"))
        out.append(
            scale(
                ev,
                widest[0],
                SCALE_BACKOFF,
                f"{note}: scale down the largest-range factor {widest[0]['name']}",
            )
        )
    fastest = fastest_factor(ev)
    if fastest is not None and widest and fastest["name"] != widest[0]["name"]:
        out.append(saturate(ev, fastest, f"{note}: clip the fastest-varying factor {fastest['name']}"))
    return out


def propose(context: dict[str, Any]) -> dict[str, Any]:
    """The Appendix A reply: ranked candidates, each one edit plus the complete revised factor set."""
    ev = parse_evidence(context)
    ranked: list[RankedEdit] = []
    order = 0
    escape = add_escape_potential(ev) if "Add" in ev.allowed else None
    if escape is not None:  # the plateau detector's report is why this request was made: that is the answer
        return {"candidates": [RankedEdit(escape[0], escape[1], 0.0, 0).to_json()], "engineer": OFFLINE_ENGINEER_LABEL}
    for edit, factors in add_unexplained(ev) if "Add" in ev.allowed else []:
        # Evidence that the program cannot express the returns outranks every diagnostic rule.
        ranked.append(RankedEdit(edit, factors, 1000.0 - order, order))
        order += 1
    if ev.guided:
        strengths = _strengths(ev)
        for metric in sorted(strengths, key=lambda m: (-strengths[m], METRICS.index(m))):
            for rank, proposal in enumerate(_rule_candidates(ev, metric)):
                if proposal is not None and proposal[0]["operator"] in ev.allowed:
                    # Primaries of every fired rule come before any rule's alternative.
                    ranked.append(
                        RankedEdit(proposal[0], proposal[1], strengths[metric] - 100.0 * rank, order)
                    )
                    order += 1
    if not ranked:
        for proposal in _generic(ev):
            if proposal is not None and proposal[0]["operator"] in ev.allowed:
                ranked.append(RankedEdit(proposal[0], proposal[1], -float(order), order))
                order += 1
    ranked.sort(key=lambda c: (-c.strength, c.order))
    chosen: list[RankedEdit] = []
    seen: set[str] = set()
    for cand in ranked:
        signature = json.dumps(cand.factors, sort_keys=True)
        if signature in seen:
            continue
        seen.add(signature)
        chosen.append(cand)
        if len(chosen) >= ev.max_candidates:
            break
    return {"candidates": [c.to_json() for c in chosen], "engineer": OFFLINE_ENGINEER_LABEL}
