"""LSFS for the offline engineer: the initial factor program, synthesised by rules from the task card.

For HalfCheetah and HumanoidStandup it returns the paper's own initial sets (section 5.3), so the
case studies can be reproduced without an LLM (HumanoidStandup's without the paper's constant survival
term, which only the decomposition's bias can weigh and the checker warns about); for any other card
it matches the card's named features (names, units, docs) to four roles — progress, posture,
stability, effort — the way a reward engineer would sketch a first draft.

Constants (chosen so that, over the states a policy visits, the factors are of comparable size —
O(1) to O(10) — and none drowns the others in the potential's attention):

* HalfCheetah: ``r_vel = v_x`` (running speeds 0–12 m/s); ``r_upright = -1.0 θ²`` (−10 when flipped,
  θ ≈ π); ``r_stable = -0.05 ω²`` (−1.25 at a brisk 5 rad/s, −20 in a somersault at 20 rad/s);
  ``r_ctrl = -0.1 Σa²`` (the environment's own control-cost weight; ≥ −0.6 for 6 actions in [−1, 1]).
* HumanoidStandup: ``r_height = 1.0 z`` (0.1 lying → 1.4 m standing);
  ``r_stable = -0.05 (v² + ω²)`` over the torso's 3 linear and 3 angular velocities (−0.65 for
  2 m/s and 3 rad/s); ``r_ctrl = -0.1 Σa²`` (≥ −1.7 for 17 actions).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

from mira.engineer.factorcode import format_range, make_factor, num
from mira.llm.base import OFFLINE_ENGINEER_LABEL, LLMRequestRejectedError

C_UPRIGHT = 1.0
C_STABLE = 0.05
C_CTRL = 0.1
C_HEIGHT = 1.0
#: Squared-rate magnitude per stability term used to state a range hint ((≈7 rad/s)²).
STABLE_TERM_BOUND = 50.0


@dataclass(frozen=True)
class CardFeature:
    name: str
    units: str
    doc: str
    better: str | None = None
    """The card's declared preference: ``higher``, ``lower`` or ``closer`` (to ``target``)."""
    target: float = 0.0
    range: tuple[float, float] | None = None
    """[min, max] over the sandbox's real states, when the request carries it."""


def parse_features(raw: Any) -> list[CardFeature]:
    """The card's features from ``context["features"]`` (name required; units and doc optional)."""
    if not isinstance(raw, list):
        raise LLMRequestRejectedError(
            "offline engineer: context['features'] must be a list of {name, units, doc}"
        )
    out: list[CardFeature] = []
    for item in raw:
        if isinstance(item, str):
            item = {"name": item}
        if not isinstance(item, dict) or not isinstance(item.get("name"), str):
            raise LLMRequestRejectedError(f"offline engineer: feature entry {item!r} has no name")
        name = item["name"]
        if not name.isidentifier() or name == "obs":
            continue
        better = item.get("better") if item.get("better") in ("higher", "lower", "closer") else None
        target = item.get("target")
        rng = item.get("range")
        bounds = None
        if isinstance(rng, list | tuple) and len(rng) == 2 and all(isinstance(v, int | float) for v in rng):
            bounds = (float(min(rng)), float(max(rng)))
        out.append(CardFeature(name, str(item.get("units") or ""), str(item.get("doc") or ""), better,
                               float(target) if isinstance(target, int | float) else 0.0, bounds))
    return out


def _hint(lo: float, hi: float) -> str:
    """A range hint around observed values: a policy that learns goes beyond a random one's states, so the
    observed span is widened by half of itself on each side."""
    pad = 0.5 * max(hi - lo, 1e-3)
    return format_range(float(f"{lo - pad:.3g}"), float(f"{hi + pad:.3g}"))


def _height_factor(height: CardFeature, role: str) -> dict[str, Any]:
    """The height term, as progress on a task to rise or as posture elsewhere (only its doc differs)."""
    return make_factor("r_height", "PHI", f"{num(C_HEIGHT)} * s.{height.name}",
                       doc=f"{role}: {height.doc or height.name}", units=height.units or "m",
                       range_hint=_hint(*height.range) if height.range else "[0, 2]")


def _square_hint(features: list[CardFeature], coef: float, bound: float) -> str:
    """Range hint of ``-coef · Σ f²``: from the observed ranges (widened), else ``bound`` per term."""
    worst = sum(max(f.range[0] ** 2, f.range[1] ** 2) * 2.25 if f.range else bound for f in features)
    return format_range(float(f"{-coef * worst:.3g}"), 0.0)


def declared_factor(f: CardFeature) -> dict[str, Any]:
    """The factor a declared preference asks for: ``s.f`` (higher), ``-s.f`` (lower) or ``-(s.f - t)²``
    (closer to t); its range hint from the feature's observed range."""
    lo, hi = f.range if f.range is not None else (-1.0, 1.0)
    if f.better == "higher":
        expr, hint, units = f"s.{f.name}", _hint(lo, hi), f.units or "1"
    elif f.better == "lower":
        expr, hint, units = f"-1.0 * s.{f.name}", _hint(-hi, -lo), f.units or "1"
    else:
        t = f.target
        dev = f"s.{f.name}" if t == 0 else f"(s.{f.name} - {num(t)})"
        worst = max((lo - t) ** 2, (hi - t) ** 2)
        expr, hint = f"-1.0 * {dev} ** 2", format_range(float(f"{-2.25 * worst:.3g}"), 0.0)
        units = f"({f.units})^2" if f.units else "1"
    factor = make_factor(f"r_{f.name}", "PHI", expr, doc=f"{f.doc or f.name} (the card: better {f.better}"
                         + (f" to {f.target:g}" if f.better == "closer" else "") + ")", units=units, range_hint=hint)
    factor["polarity"] = "reward" if f.better == "higher" else "penalty"
    return factor


def _has(features: list[CardFeature], *names: str) -> bool:
    present = {f.name for f in features}
    return all(n in present for n in names)


def _sq_sum(names: list[str]) -> str:
    return " + ".join(f"np.square(s.{n})" for n in names)


def _ctrl(action_dim: int) -> dict[str, Any]:
    return make_factor(
        "r_ctrl",
        "AUX",
        f"-{num(C_CTRL)} * np.sum(a * a, axis=-1)",
        doc="control effort: squared action magnitude, penalised",
        units="N^2",
        range_hint=format_range(-C_CTRL * max(action_dim, 1), 0.0),
    )


def halfcheetah_program(action_dim: int) -> list[dict[str, Any]]:
    """The paper's HalfCheetah F(0) = {r_vel, r_upright, r_stable | r_ctrl} (section 5.3.1)."""
    return [
        make_factor(
            "r_vel",
            "PHI",
            "s.x_velocity",
            doc="forward velocity of the torso (progress along +x)",
            units="m/s",
            range_hint="[-15, 15]",
        ),
        make_factor(
            "r_upright",
            "PHI",
            f"-{num(C_UPRIGHT)} * np.square(s.pitch)",
            doc="posture: squared torso pitch, penalised (0 when level)",
            units="rad^2",
            range_hint="[-10, 0]",
        ),
        make_factor(
            "r_stable",
            "PHI",
            f"-{num(C_STABLE)} * np.square(s.pitch_rate)",
            doc="stability: squared pitch angular rate, penalised",
            units="rad^2/s^2",
            range_hint="[-20, 0]",
        ),
        _ctrl(action_dim),
    ]


STANDUP_RATIONALE = (
    "The paper's initial set for this task (section 5.3.2) less its survival constant c2: a per-step "
    "constant carries no information about the state or the action, and the decomposition's bias already "
    "fits it."
)
_STANDUP_RATES = ["x_velocity", "y_velocity", "z_velocity", "roll_rate", "pitch_rate", "yaw_rate"]


def humanoidstandup_program(action_dim: int) -> list[dict[str, Any]]:
    """The paper's HumanoidStandup F(0) less its survival constant: {r_height, r_stable | r_ctrl} (5.3.2)."""
    return [
        make_factor(
            "r_height",
            "PHI",
            f"{num(C_HEIGHT)} * s.torso_height",
            doc="height of the torso above the floor (upward progress)",
            units="m",
            range_hint="[0, 1.5]",
        ),
        make_factor(
            "r_stable",
            "PHI",
            f"-{num(C_STABLE)} * ({_sq_sum(_STANDUP_RATES)})",
            doc="stability: squared linear (vx, vy, vz) and angular (roll, pitch, yaw) torso velocities, "
            "penalised",
            units="m^2/s^2 + rad^2/s^2",
            range_hint=format_range(-C_STABLE * STABLE_TERM_BOUND * len(_STANDUP_RATES), 0.0),
        ),
        _ctrl(action_dim),
    ]


def _direction(description: str) -> tuple[str, float]:
    """Axis and sign of the progress the description asks for (default: forward, +x)."""
    m = re.search(r"([+-])\s*([xyz])\b", description)
    if m:
        return m.group(2), (-1.0 if m.group(1) == "-" else 1.0)
    if "backward" in description:
        return "x", -1.0
    if "sideways" in description or "lateral" in description:
        return "y", 1.0
    return "x", 1.0


def _velocity_feature(features: list[CardFeature], axis: str) -> CardFeature | None:
    pattern = re.compile(rf"^(v_?{axis}|{axis}_?vel(ocity)?|vel(ocity)?_?{axis})$")
    for f in features:
        if pattern.match(f.name):
            return f
    if axis == "x":
        for f in features:
            if "m/s" in f.units and "forward" in f.doc.lower():
                return f
    return None


def _height_feature(features: list[CardFeature]) -> CardFeature | None:
    for f in features:
        if "height" in f.name or (f.units == "m" and "height" in f.doc.lower()):
            return f
    return None


def _is_height_task(task: str, description: str) -> bool:
    return "standup" in task or bool(
        re.search(
            r"\bstand(s|ing)? up\b|\bget(s|ting)? up\b|\brise\b|\bjump|\blift(ed|s)? (the )?torso",
            description,
        )
    )


def generic_program(features: list[CardFeature], action_dim: int, task: str, description: str
                    ) -> tuple[list[dict], list[str]]:
    """The factors and the rationale's lines for any card.

    A feature whose card entry declares ``better`` gets the factor that preference asks for, and when any
    does, the undeclared ones are left out. A card that declares none is matched to roles by name and
    units only (progress: the velocity along the direction the
    description names, or the height when the task is to rise; posture: angles in rad, as a squared
    penalty; stability: angular rates, as a squared penalty); what none of that covers is listed in the
    rationale as unused, with the reason. No constant factor is written: a per-step constant (a survival
    bonus) is what the decomposition's bias already fits.
    """
    desc = description.lower()
    factors: list[dict[str, Any]] = []
    used: set[str] = set()
    notes: list[str] = []
    for f in features:
        if f.better is not None:
            factors.append(declared_factor(f))
            used.add(f.name)
            notes.append(f"{f.name}: r_{f.name}, as the card declares (better {f.better}).")
    if used:  # the card says which features matter and how: the others are left out, not guessed
        if action_dim > 0:
            factors.append(_ctrl(action_dim))
        notes += [f"{f.name}: not used; the card declares no preference for it (its key 'better')."
                  for f in features if f.name not in used]
        return factors, notes
    height = _height_feature([f for f in features if f.name not in used])
    height_task = _is_height_task(task.lower(), desc) and height is not None
    # Progress.
    if height_task and height is not None:
        factors.append(_height_factor(height, "upward progress"))
        used.add(height.name)
    else:
        axis, sign = _direction(desc)
        vel = _velocity_feature([f for f in features if f.name not in used], axis)
        if vel is not None:
            expr = f"s.{vel.name}" if sign > 0 else f"-s.{vel.name}"
            factors.append(
                make_factor(
                    "r_vel",
                    "PHI",
                    expr,
                    doc=f"progress: {vel.doc or vel.name}"
                    + (" (negated: the task asks for -" + axis + ")" if sign < 0 else ""),
                    units=vel.units or "m/s",
                    range_hint=(_hint(*vel.range) if sign > 0 else _hint(-vel.range[1], -vel.range[0]))
                    if vel.range else "[-10, 10]",
                )
            )
            used.add(vel.name)
    # Posture: angles (in rad) are better near 0.
    angles = [f for f in features if f.name not in used and (
        f.name in ("pitch", "roll") or f.name.endswith(("_pitch", "_roll", "_angle", "_tilt"))) and (
        f.units in ("", "rad"))]
    if angles:
        names = [f.name for f in angles]
        factors.append(
            make_factor(
                "r_upright",
                "PHI",
                f"-{num(C_UPRIGHT)} * ({_sq_sum(names)})",
                doc="posture: squared " + " and ".join(names) + ", penalised (0 = level)",
                units="rad^2",
                range_hint=_square_hint(angles, C_UPRIGHT, 10.0),
            )
        )
        used.update(names)
    if height is not None and height.name not in used:
        factors.append(_height_factor(height, "posture"))
        used.add(height.name)
    if re.search(r"without falling|surviv|alive|terminat", desc):
        notes.append("No survival bonus: a per-step constant is what the decomposition's bias fits.")
    # Stability: angular rates (and, when the task is to rise, the linear velocities too).
    rates = [
        f.name
        for f in features
        if f.name not in used
        and ("rad/s" in f.units or f.name.endswith("_rate") or "angular" in f.doc.lower())
    ]
    if height_task:
        rates = [
            f.name for f in features if f.name not in used and "m/s" in f.units and f.name not in rates
        ] + rates
    if rates:
        factors.append(
            make_factor(
                "r_stable",
                "PHI",
                f"-{num(C_STABLE)} * ({_sq_sum(rates)})",
                doc="stability: squared " + ", ".join(rates) + ", penalised",
                units="squared rates",
                range_hint=_square_hint([f for f in features if f.name in rates], C_STABLE, STABLE_TERM_BOUND),
            )
        )
    if not any(f["type"] == "PHI" for f in factors):
        raise LLMRequestRejectedError(
            f"offline engineer: task card {task!r} names no feature it recognises as progress, posture or "
            "stability (e.g. x_velocity, torso_height, pitch, uprightness, *_rate); write the program by "
            "hand or use an LLM backend"
        )
    if action_dim > 0:
        factors.append(_ctrl(action_dim))
    declared = {f"r_{feat.name}" for feat in features if feat.better is not None}
    notes += [f"{factor['name']}: {factor['doc']}." for factor in factors if factor["name"] not in declared]
    for feat in features:
        if feat.name not in used and not any(f"s.{feat.name}" in factor["code"] for factor in factors):
            notes.append(f"{feat.name}: not used; the card declares no preference for it (its key 'better') and "
                         "its name and units match no role.")
    return factors, notes


def synthesize(context: dict[str, Any]) -> dict[str, Any]:
    """The initial program F(0) for the card described by ``context`` (see module docstring)."""
    task = context.get("task")
    if not isinstance(task, str) or not task:
        raise LLMRequestRejectedError("offline engineer: LSFS needs context['task'] (the task card's name)")
    features = parse_features(context.get("features"))
    try:
        action_dim = int(context.get("action_dim") or 0)
    except (TypeError, ValueError):
        raise LLMRequestRejectedError("offline engineer: context['action_dim'] must be an integer") from None
    description = str(context.get("description") or "")
    key = task.lower()
    if key == "halfcheetah" and _has(features, "x_velocity", "pitch", "pitch_rate"):
        factors = halfcheetah_program(action_dim)
    elif key == "humanoidstandup" and _has(features, "torso_height", *_STANDUP_RATES):
        return {"task": task, "version": 0, "factors": humanoidstandup_program(action_dim),
                "rationale": STANDUP_RATIONALE, "engineer": OFFLINE_ENGINEER_LABEL}
    else:
        factors, notes = generic_program(features, action_dim, task, description)
        return {"task": task, "version": 0, "factors": factors, "rationale": " ".join(notes),
                "engineer": OFFLINE_ENGINEER_LABEL}
    return {"task": task, "version": 0, "factors": factors, "engineer": OFFLINE_ENGINEER_LABEL}
