"""What the offline engineer reads from an SRR request: its ``context``, checked and normalised.

The engineer sees only what the request carries (what an LLM is sent, as JSON), never MIRA's objects,
so it is held to the same information; a malformed context is refused with
:class:`~mira.llm.base.LLMRequestRejectedError`, as a remote endpoint would refuse a bad request.
"""

from __future__ import annotations

import copy
import json
import math
from dataclasses import dataclass, field
from typing import Any

from mira.engineer.factorcode import features_used
from mira.engineer.srr_prompt import return_is_poor
from mira.llm.base import LLMRequestRejectedError
from mira.shaping.attribution import residual_share

OPERATORS: tuple[str, ...] = ("Scale", "Sat", "Gate", "Refactor", "Add", "Prune")
METRICS: tuple[str, ...] = ("PEG", "TPD", "PVC", "FAP", "RPE")


@dataclass
class RequestContext:
    """An SRR request's ``context`` as the offline engineer reads it, checked and normalised.

    Not :class:`mira.engineer.srr_prompt.Evidence`: the engineer sees only what the request carries
    (what an LLM is sent, as JSON), never MIRA's objects, so it is held to the same information."""

    factors: list[dict[str, Any]]
    z: dict[str, float]
    raw: dict[str, float]
    grad: dict[str, float]
    recent_mean: float | None
    baseline: float | None
    band: dict[str, float | str] | None
    posture: str | None
    max_candidates: int
    allowed: tuple[str, ...]
    guided: bool
    feature_names: list[str]
    attention: dict[str, float] = field(default_factory=dict)
    unexplained: list[dict[str, Any]] = field(default_factory=list)
    """Task features that explain returns the program cannot, largest gain first: ``{feature, form
    ('value' or 'neg_square'), gain, share, cv_r2, range}`` (see :mod:`mira.shaping.attribution`)."""
    program_r2: float | None = None
    """The program's own out-of-sample R² of the returns, when the request carries it."""
    plateau: dict[str, Any] | None = None
    """The plateau detector's report (feature, center, halfwidth, visited range, reward per step) when the
    request carries a well-formed one."""

    @property
    def poor_return(self) -> bool:
        """Return is not improving on its baseline (unknown counts as poor: MCM fired anyway)."""
        return return_is_poor(self.recent_mean, self.baseline)


def _floats(raw: Any) -> dict[str, float]:
    out: dict[str, float] = {}
    if isinstance(raw, dict):
        for key in METRICS:
            value = raw.get(key)
            if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
                out[key] = float(value)
    return out


def _opt_float(value: Any) -> float | None:
    if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
        return float(value)
    return None


def parse_evidence(context: dict[str, Any]) -> RequestContext:
    program = context.get("program")
    if isinstance(program, str):
        try:
            program = json.loads(program)
        except json.JSONDecodeError:
            program = None
    if not isinstance(program, dict) or not isinstance(program.get("factors"), list):
        raise LLMRequestRejectedError("offline engineer: SRR needs context['program'] with a 'factors' list")
    factors: list[dict[str, Any]] = []
    for f in program["factors"]:
        if not (
            isinstance(f, dict)
            and isinstance(f.get("name"), str)
            and isinstance(f.get("code"), str)
            and f.get("type") in ("PHI", "AUX", "SHAPE")
        ):
            raise LLMRequestRejectedError(f"offline engineer: malformed factor in context['program']: {f!r}")
        factors.append(copy.deepcopy(f))
    trend_raw = context.get("return_trend")
    trend: dict[str, Any] = trend_raw if isinstance(trend_raw, dict) else {}
    band_raw = context.get("stagnation_band")
    band: dict[str, float | str] | None = None
    if isinstance(band_raw, dict):
        center, half = _opt_float(band_raw.get("center")), _opt_float(band_raw.get("halfwidth"))
        feat = band_raw.get("feature", "torso_height")
        if center is not None and half is not None and isinstance(feat, str) and feat.isidentifier():
            band = {"feature": feat, "center": center, "halfwidth": abs(half)}
    allowed_raw = context.get("allowed_operators")
    allowed = tuple(op for op in OPERATORS if allowed_raw is None or op in allowed_raw)
    try:
        max_candidates = int(context.get("max_candidates", 3))
    except (TypeError, ValueError):
        raise LLMRequestRejectedError(
            "offline engineer: context['max_candidates'] must be an integer"
        ) from None
    names: list[str] = []
    for item in context.get("features") or []:
        name = item.get("name") if isinstance(item, dict) else item
        if isinstance(name, str) and name not in names:
            names.append(name)
    for f in factors:
        for name in features_used(f["code"]):
            if name not in names and name != "obs":
                names.append(name)
    posture = context.get("posture_feature")
    attention_raw = context.get("factor_attention")
    attention = {
        str(k): float(v)
        for k, v in (attention_raw.items() if isinstance(attention_raw, dict) else [])
        if isinstance(v, int | float) and math.isfinite(v)
    }
    guided = bool(context.get("guided", True))
    program_r2, unexplained = _attribution(context.get("return_attribution"), names)
    return RequestContext(
        factors=factors,
        z=_floats(context.get("diagnostics")) if guided else {},
        raw=_floats(context.get("raw_diagnostics")) if guided else {},
        grad=_floats(context.get("gradient")) if guided else {},
        recent_mean=_opt_float(trend.get("recent_mean")),
        baseline=_opt_float(trend.get("baseline")),
        band=band if guided else None,
        posture=posture if isinstance(posture, str) and posture.isidentifier() else None,
        max_candidates=max(max_candidates, 0),
        allowed=allowed,
        guided=guided,
        feature_names=names,
        attention=attention,
        unexplained=unexplained if guided else [],
        program_r2=program_r2 if guided else None,
        plateau=_plateau(context.get("plateau"), names) if guided else None,
    )


def _plateau(raw: Any, features: list[str]) -> dict[str, Any] | None:
    """``context['plateau']`` when it names one of the card's features and carries finite figures."""
    if not isinstance(raw, dict) or raw.get("feature") not in features:
        return None
    visited = raw.get("visited")
    out: dict[str, Any] = {"feature": raw["feature"]}
    for key in ("center", "halfwidth", "reward_per_step"):
        out[key] = _opt_float(raw.get(key))
    lo, hi = (_opt_float(visited[0]), _opt_float(visited[1])) if isinstance(visited, list) and len(visited) == 2 \
        else (None, None)
    if any(v is None for v in out.values()) or lo is None or hi is None:
        return None
    out["visited"] = (min(lo, hi), max(lo, hi))
    out["start"] = _opt_float(raw.get("start"))  # None: not reported (evidence from before it was)
    return out


def _attribution(raw: Any, features: list[str]) -> tuple[float | None, list[dict[str, Any]]]:
    """The well-formed entries of ``context['return_attribution']`` about the card's own features."""
    if not isinstance(raw, dict):
        return None, []
    out: list[dict[str, Any]] = []
    program_r2 = _opt_float(raw.get("program_cv_r2"))
    for item in raw.get("feature_gains") or []:
        if not isinstance(item, dict):
            continue
        name, form, gain = item.get("feature"), item.get("form"), _opt_float(item.get("gain"))
        rng = item.get("range")
        if not (isinstance(name, str) and name in features and form in ("value", "neg_square") and gain is not None):
            continue
        lo = hi = None
        if isinstance(rng, list) and len(rng) == 2:
            lo, hi = _opt_float(rng[0]), _opt_float(rng[1])
        share = _opt_float(item.get("share"))
        if share is None and program_r2 is not None:  # an attribution written before shares were
            share = residual_share(gain, program_r2)
        out.append({"feature": name, "form": form, "gain": gain, "share": share,
                    "cv_r2": _opt_float(item.get("cv_r2")),
                    "range": None if lo is None or hi is None else (min(lo, hi), max(lo, hi))})
    out.sort(key=lambda e: -e["gain"])
    return program_r2, out
