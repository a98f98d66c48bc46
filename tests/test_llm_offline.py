"""The offline rule-based reward engineer: paper's initial sets, section 4.4.2 rules, determinism."""

from __future__ import annotations

import ast
import copy
import json
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mira.engineer.offline import OfflineEngineer
from mira.llm.base import OFFLINE_ENGINEER_LABEL, LLMRequest, LLMRequestRejectedError
from mira.tasks.card import load_task

ALLOWED_NP = {
    "tanh", "exp", "clip", "square", "abs", "sqrt", "minimum", "maximum", "where", "sum", "cos", "sin",
    "ones_like", "zeros_like",
}  # fmt: skip
ALLOWED_NODES = (
    ast.Module, ast.FunctionDef, ast.arguments, ast.arg, ast.Return, ast.Assign, ast.Name, ast.Load,
    ast.Store, ast.Attribute, ast.Call, ast.keyword, ast.BinOp, ast.UnaryOp, ast.Constant, ast.Add,
    ast.Sub, ast.Mult, ast.Div, ast.USub, ast.Pow,
)  # fmt: skip


def _card_context(task: str, action_dim: int) -> dict[str, Any]:
    card = load_task(task)
    return {
        "task": card.name,
        "features": [{"name": f.name, "units": f.units, "doc": f.doc, "better": f.better, "target": f.target}
                     for f in card.features],
        "action_dim": action_dim,
        "description": card.description,
    }


def _ask(purpose: str, context: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    req = LLMRequest(messages=[{"role": "user", "content": "..."}], purpose=purpose, context=context)  # type: ignore[arg-type]
    out = OfflineEngineer().complete(req)
    assert (out.backend, out.model) == ("offline", "rule-based-engineer-v2")
    return out.content, json.loads(out.content)


def _check_factor(factor: dict[str, Any], features: list[str], action_dim: int) -> np.ndarray:
    """Admissible syntax only, the right signature, and a finite [B] result on a random batch."""
    assert set(factor) >= {"name", "type", "code", "doc", "units", "range_hint"}
    code = factor["code"]
    assert code.startswith(
        f"def {factor['name']}(s, a):\n" if factor["type"] == "AUX" else f"def {factor['name']}(s):\n"
    )
    assert all(line.startswith("    ") for line in code.splitlines()[1:])
    tree = ast.parse(code)
    for node in ast.walk(tree):
        assert isinstance(node, ALLOWED_NODES), f"{factor['name']}: {type(node).__name__} not admissible"
        if isinstance(node, ast.Constant):
            assert isinstance(node.value, int | float), f"{factor['name']}: non-numeric constant"
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            if node.value.id == "np":
                assert node.attr in ALLOWED_NP, node.attr
            elif node.value.id == "s":
                assert node.attr in features, node.attr
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load):
            assert node.id in ("s", "a", "np"), node.id
    if factor["type"] == "PHI":
        assert not any(isinstance(n, ast.Name) and n.id == "a" for n in ast.walk(tree))
    rng = np.random.default_rng(0)
    batch = 64
    state = SimpleNamespace(**{f: rng.normal(size=batch) for f in features})
    namespace: dict[str, Any] = {"np": np}
    exec(compile(tree, "<factor>", "exec"), namespace)
    fn = namespace[factor["name"]]
    args = (state, rng.uniform(-1, 1, size=(batch, action_dim))) if factor["type"] == "AUX" else (state,)
    out = np.asarray(fn(*args))
    assert out.shape == (batch,) and np.all(np.isfinite(out))
    return out


def test_halfcheetah_lsfs_is_the_papers_initial_set() -> None:
    ctx = _card_context("halfcheetah", 6)
    _, program = _ask("lsfs", ctx)
    assert program["task"] == "halfcheetah" and program["version"] == 0
    assert program["engineer"] == OFFLINE_ENGINEER_LABEL
    factors = {f["name"]: f for f in program["factors"]}
    assert list(factors) == ["r_vel", "r_upright", "r_stable", "r_ctrl"]
    assert [f["type"] for f in program["factors"]] == ["PHI", "PHI", "PHI", "AUX"]
    assert factors["r_vel"]["code"] == "def r_vel(s):\n    return s.x_velocity\n"
    assert factors["r_upright"]["code"] == "def r_upright(s):\n    return -1.0 * np.square(s.pitch)\n"
    assert factors["r_stable"]["code"] == "def r_stable(s):\n    return -0.05 * np.square(s.pitch_rate)\n"
    assert factors["r_ctrl"]["code"] == "def r_ctrl(s, a):\n    return -0.1 * np.sum(a * a, axis=-1)\n"
    names = [f["name"] for f in ctx["features"]]
    for f in program["factors"]:
        _check_factor(f, names, 6)


def test_humanoidstandup_lsfs_is_the_papers_initial_set_less_its_constant() -> None:
    ctx = _card_context("humanoidstandup", 17)
    _, program = _ask("lsfs", ctx)
    factors = {f["name"]: f for f in program["factors"]}
    assert list(factors) == ["r_height", "r_stable", "r_ctrl"]
    assert [f["type"] for f in program["factors"]] == ["PHI", "PHI", "AUX"]
    assert "s.torso_height" in factors["r_height"]["code"]
    assert "survival constant" in program["rationale"]
    for feat in ("x_velocity", "y_velocity", "z_velocity", "roll_rate", "pitch_rate", "yaw_rate"):
        assert f"np.square(s.{feat})" in factors["r_stable"]["code"]
    assert factors["r_ctrl"]["range_hint"] == "[-1.7, 0]"
    names = [f["name"] for f in ctx["features"]]
    values = {f["name"]: _check_factor(f, names, 17) for f in program["factors"]}
    assert np.all(values["r_stable"] <= 0) and np.all(values["r_ctrl"] <= 0)


def test_declared_preferences_decide_the_factors_not_words_in_the_docs() -> None:
    """A feature documented "0 = upright" becomes a reward for leaning when a word decides; its declared
    ``better = "closer"`` makes it a penalty on the deviation. Undeclared features are left out, with the
    reason in the rationale, and no constant factor is written."""
    ctx = {
        "task": "hopper-like",
        "features": [
            {"name": "torso_angle", "units": "rad", "doc": "tilt of the torso, 0 = upright", "better": "closer",
             "target": 0.0, "range": [-0.3, 0.2]},
            {"name": "speed_x", "units": "m/s", "doc": "forward speed", "better": "higher", "range": [-1.0, 2.0]},
            {"name": "fuel", "units": "kg", "doc": "fuel left", "better": "lower"},
            {"name": "knee", "units": "rad", "doc": "knee angle"},
        ],
        "action_dim": 3,
        "description": "Hop forward without falling; every step alive earns a bonus.",
    }
    _, prog = _ask("lsfs", ctx)
    codes = {f["name"]: f["code"].split("return ")[1].strip() for f in prog["factors"]}
    assert codes == {"r_torso_angle": "-1.0 * s.torso_angle ** 2", "r_speed_x": "s.speed_x",
                     "r_fuel": "-1.0 * s.fuel", "r_ctrl": "-0.1 * np.sum(a * a, axis=-1)"}
    hints = {f["name"]: f["range_hint"] for f in prog["factors"]}
    assert hints["r_speed_x"] == "[-2.5, 3.5]" and hints["r_torso_angle"] == "[-0.202, 0]"
    assert "knee: not used" in prog["rationale"]
    for f in prog["factors"]:
        _check_factor(f, [x["name"] for x in ctx["features"]], 3)


@pytest.mark.parametrize("task", ["halfcheetah", "humanoidstandup", "hopper", "swimmer", "humanoid"])
def test_synthesised_programs_of_built_in_cards_draw_no_checker_warnings(task: str) -> None:
    from mira.engineer.lsfs import synthesize_program
    from mira.engineer.offline import OfflineEngineer
    from mira.factors.checker import check_program
    from mira.factors.sandbox import sandbox_check
    from mira.tasks.envs import action_dim

    card = load_task(task)
    program = synthesize_program(card, OfflineEngineer(), action_dim(card)).program
    assert not check_program(program, card).warnings
    report = sandbox_check(program, card)
    assert report.ok and not any(v.warnings for v in report.factors.values()), report.lines()


def test_other_cards_get_a_synthesised_program() -> None:
    ctx = _card_context("humanoid", 17)
    _, program = _ask("lsfs", ctx)
    factors = {f["name"]: f for f in program["factors"]}
    # The card declares which way is good for x_velocity, torso_height and uprightness: those are the factors.
    assert factors["r_x_velocity"]["code"] == "def r_x_velocity(s):\n    return s.x_velocity\n"
    assert factors["r_uprightness"]["code"] == "def r_uprightness(s):\n    return s.uprightness\n"
    assert set(factors) == {"r_x_velocity", "r_torso_height", "r_uprightness", "r_ctrl"}
    assert factors["r_ctrl"]["type"] == "AUX" and "roll_rate: not used" in program["rationale"]
    names = [f["name"] for f in ctx["features"]]
    for f in program["factors"]:
        _check_factor(f, names, 17)
    custom = {
        "task": "hopper-up",
        "features": [
            {"name": "torso_height", "units": "m", "doc": "torso height"},
            {"name": "z_velocity", "units": "m/s", "doc": "vertical velocity"},
            {"name": "pitch", "units": "rad", "doc": "torso pitch"},
            {"name": "pitch_rate", "units": "rad/s", "doc": "pitch rate"},
        ],
        "action_dim": 3,
        "description": "Make the hopper stand up and stay upright.",
    }
    _, prog = _ask("lsfs", custom)
    assert prog["factors"][0]["name"] == "r_height"
    for f in prog["factors"]:
        _check_factor(f, [x["name"] for x in custom["features"]], 3)


def test_lsfs_without_recognisable_features_is_rejected() -> None:
    with pytest.raises(LLMRequestRejectedError, match="recognises"):
        _ask("lsfs", {"task": "blob", "features": [{"name": "q0", "units": "", "doc": ""}], "action_dim": 2})
    with pytest.raises(LLMRequestRejectedError, match="context"):
        _ask("srr", {})


def _srr_context(task: str, action_dim: int, **overrides: Any) -> dict[str, Any]:
    card_ctx = _card_context(task, action_dim)
    _, program = _ask("lsfs", card_ctx)
    ctx: dict[str, Any] = {
        "program": program,
        "features": card_ctx["features"],
        "diagnostics": {"PEG": 0.1, "TPD": 0.2, "PVC": 0.1, "FAP": 0.1, "RPE": 0.2},
        "raw_diagnostics": {"PEG": 0.0, "TPD": 0.01, "PVC": 0.6, "FAP": 0.05, "RPE": 0.2},
        "anomaly_score": 9.5,
        "gradient": {"PEG": 0.0, "TPD": 0.0, "PVC": 0.0, "FAP": 0.0, "RPE": 0.0},
        "top_contributors": [],
        "return_trend": {"recent_mean": 100.0, "baseline": 90.0},
        "stagnation_band": None,
        "posture_feature": "pitch" if task == "halfcheetah" else "uprightness",
        "max_candidates": 3,
        "allowed_operators": ["Scale", "Sat", "Gate", "Refactor", "Add", "Prune"],
        "guided": True,
    }
    ctx.update(overrides)
    return ctx


def _check_candidates(reply: dict[str, Any], ctx: dict[str, Any], action_dim: int) -> None:
    assert reply["engineer"] == OFFLINE_ENGINEER_LABEL
    assert len(reply["candidates"]) <= ctx["max_candidates"]
    names = [f["name"] for f in ctx["features"]]
    for cand in reply["candidates"]:
        for edit in cand["edits"]:
            assert set(edit) == {"operator", "targets", "params", "justification"}
            assert edit["operator"] in ctx["allowed_operators"] and edit["justification"]
        for f in cand["updated_factors"]:
            _check_factor(f, names, action_dim)


def test_srr_low_pvc_gates_velocity_on_posture() -> None:
    ctx = _srr_context(
        "halfcheetah",
        6,
        diagnostics={"PEG": 0.2, "TPD": 0.3, "PVC": -2.6, "FAP": 0.0, "RPE": 0.4},
        raw_diagnostics={"PEG": 0.0, "TPD": 0.01, "PVC": -0.45, "FAP": 0.05, "RPE": 0.3},
        gradient={"PEG": 0.0, "TPD": 0.0, "PVC": 1.9, "FAP": 0.0, "RPE": 0.0},
    )
    _, reply = _ask("srr", ctx)
    _check_candidates(reply, ctx, 6)
    best = reply["candidates"][0]
    (edit,) = best["edits"]
    assert edit["operator"] == "Gate" and edit["targets"] == ["r_vel"]
    assert edit["params"]["gate_code"] == "1.0 - np.tanh(2.0 * np.square(s.pitch))"
    assert edit["params"]["alpha"] == 2.0 and "PVC" in edit["justification"]
    r_vel = next(f for f in best["updated_factors"] if f["name"] == "r_vel")
    assert r_vel["type"] == "PHI"
    assert (
        r_vel["code"]
        == "def r_vel(s):\n    return s.x_velocity * (1.0 - np.tanh(2.0 * np.square(s.pitch)))\n"
    )
    assert [f["name"] for f in best["updated_factors"]] == ["r_vel", "r_upright", "r_stable", "r_ctrl"]
    assert reply["candidates"][1]["edits"][0]["operator"] == "Refactor"
    assert "np.cos(s.pitch)" in reply["candidates"][1]["edits"][0]["params"]["expression"]
    # The gate suppresses velocity when flipped and leaves it intact when level.
    namespace: dict[str, Any] = {"np": np}
    exec(r_vel["code"], namespace)
    level = namespace["r_vel"](SimpleNamespace(x_velocity=np.array([10.0]), pitch=np.array([0.0])))
    flipped = namespace["r_vel"](SimpleNamespace(x_velocity=np.array([10.0]), pitch=np.array([np.pi])))
    assert level[0] == pytest.approx(10.0) and abs(flipped[0]) < 1e-3
    # Without Gate among the allowed operators, the Refactor comes first.
    _, no_gate = _ask("srr", {**ctx, "allowed_operators": ["Refactor", "Scale"]})
    assert no_gate["candidates"][0]["edits"][0]["operator"] == "Refactor"


def test_srr_high_rpe_with_stagnation_band_adds_a_state_only_bonus() -> None:
    ctx = _srr_context(
        "humanoidstandup",
        17,
        diagnostics={"PEG": -2.2, "TPD": 0.1, "PVC": 0.3, "FAP": 0.1, "RPE": 2.8},
        raw_diagnostics={"PEG": -0.02, "TPD": 0.01, "PVC": 0.5, "FAP": 0.05, "RPE": 0.9},
        gradient={"PEG": 1.1, "TPD": 0.0, "PVC": 0.0, "FAP": 0.0, "RPE": -2.4},
        return_trend={"recent_mean": 51000.0, "baseline": 52000.0},
        stagnation_band={"feature": "torso_height", "center": 0.45, "halfwidth": 0.05},
        max_candidates=2,
    )
    _, reply = _ask("srr", ctx)
    _check_candidates(reply, ctx, 17)
    best = reply["candidates"][0]
    (edit,) = best["edits"]
    assert edit["operator"] == "Add" and edit["targets"] == ["r_explore"]
    assert edit["params"]["z_stag"] == 0.45 and edit["params"]["halfwidth"] == 0.05
    new = best["updated_factors"][-1]
    assert new["name"] == "r_explore" and new["type"] == "PHI"
    assert "(s.torso_height - 0.45)" in new["code"] and "np.tanh(2.0 * s.z_velocity)" in new["code"]
    assert new["code"].startswith("def r_explore(s):\n") and "np.exp(" in new["code"]
    assert [f["name"] for f in best["updated_factors"][:-1]] == [
        "r_height",
        "r_stable",
        "r_ctrl",
    ]
    # Bounded, and localised: rising below the band earns ~nothing, rising at/above it earns the bonus.
    namespace: dict[str, Any] = {"np": np}
    exec(new["code"], namespace)
    z = np.array([0.1, 0.45, 0.6, 1.4])
    vals = namespace["r_explore"](SimpleNamespace(torso_height=z, z_velocity=np.full(4, 0.5)))
    assert vals[0] < 0.01 and vals[2] > vals[1] > vals[0]
    assert np.all(np.abs(vals) <= 1.5 + 1e-9)
    # With good returns the plateau rule does not fire.
    _, healthy = _ask("srr", {**ctx, "return_trend": {"recent_mean": 60000.0, "baseline": 52000.0}})
    assert all(c["edits"][0]["operator"] != "Add" for c in healthy["candidates"])


def test_srr_fap_and_tpd_rules() -> None:
    fap = _srr_context(
        "halfcheetah",
        6,
        diagnostics={"PEG": 0.0, "TPD": 0.0, "PVC": 0.2, "FAP": -2.5, "RPE": 0.0},
        raw_diagnostics={"PEG": 0.0, "TPD": 0.01, "PVC": 0.6, "FAP": 1e-5, "RPE": 0.2},
        factor_attention={"r_vel": 0.1, "r_upright": 0.1, "r_stable": 0.8},
    )
    _, reply = _ask("srr", fap)
    _check_candidates(reply, fap, 6)
    ops = [(c["edits"][0]["operator"], c["edits"][0]["targets"]) for c in reply["candidates"]]
    assert ops[0] == ("Gate", ["r_stable"]) and ("Prune", ["r_stable"]) in ops
    pruned = next(c for c in reply["candidates"] if c["edits"][0]["operator"] == "Prune")
    assert "r_stable" not in [f["name"] for f in pruned["updated_factors"]]
    tpd = _srr_context(
        "halfcheetah",
        6,
        diagnostics={"PEG": 0.0, "TPD": 3.0, "PVC": 0.2, "FAP": 0.0, "RPE": 0.0},
        return_trend={"recent_mean": 80.0, "baseline": 90.0},
    )
    _, reply = _ask("srr", tpd)
    _check_candidates(reply, tpd, 6)
    (edit,) = reply["candidates"][0]["edits"]
    assert edit["operator"] == "Sat" and edit["targets"] == ["r_stable"]
    assert "np.clip(" in reply["candidates"][0]["updated_factors"][2]["code"]


def test_srr_unguided_proposes_generic_edits() -> None:
    ctx = _srr_context("halfcheetah", 6, guided=False, diagnostics=None, raw_diagnostics=None, gradient=None)
    _, reply = _ask("srr", ctx)
    _check_candidates(reply, ctx, 6)
    ops = [c["edits"][0]["operator"] for c in reply["candidates"]]
    assert ops and set(ops) <= {"Sat", "Scale"}
    assert all("unguided" in c["edits"][0]["justification"] for c in reply["candidates"])
    _, capped = _ask("srr", {**ctx, "max_candidates": 1})
    assert len(capped["candidates"]) == 1


def test_offline_replies_are_deterministic() -> None:
    ctx = _srr_context(
        "halfcheetah",
        6,
        diagnostics={"PEG": 0.2, "TPD": 2.0, "PVC": -2.6, "FAP": -1.5, "RPE": 1.4},
        raw_diagnostics={"PEG": 0.0, "TPD": 0.2, "PVC": -0.45, "FAP": 1e-4, "RPE": 0.7},
        return_trend={"recent_mean": 1.0, "baseline": 2.0},
        stagnation_band={"feature": "torso_height", "center": -0.1, "halfwidth": 0.02},
        max_candidates=6,
    )
    first, reply = _ask("srr", copy.deepcopy(ctx))
    second, _ = _ask("srr", copy.deepcopy(ctx))
    assert first == second
    _check_candidates(reply, ctx, 6)
    assert len(reply["candidates"]) == 6
    lsfs_ctx = _card_context("humanoid", 17)
    assert _ask("lsfs", lsfs_ctx)[0] == _ask("lsfs", copy.deepcopy(lsfs_ctx))[0]
