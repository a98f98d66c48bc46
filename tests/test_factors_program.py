"""The factor-program model: JSON contract, validation, hash, diff, examples, atomic save."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mira.errors import UsageError
from mira.factors import (
    Factor,
    FactorProgram,
    ProgramParseError,
    code_diff,
    example_program,
    load_program,
    save_program,
)

CONTRACT = {
    "task": "halfcheetah",
    "version": 0,
    "factors": [
        {
            "name": "r_vel",
            "type": "PHI",
            "code": "def r_vel(s):\n    return s.x_velocity\n",
            "doc": "forward velocity of the torso",
            "units": "m/s",
            "range_hint": "[-15, 15]",
        },
        {
            "name": "r_ctrl",
            "type": "AUX",
            "code": "def r_ctrl(s, a):\n    return -np.sum(a * a, axis=-1)\n",
            "doc": "control effort",
            "units": "N^2",
            "range_hint": "[-6, 0]",
        },
    ],
}


def test_design_md_contract_round_trips() -> None:
    program = FactorProgram.from_json(CONTRACT)
    assert [f.name for f in program.phi_factors] == ["r_vel"]
    assert [f.name for f in program.aux_factors] == ["r_ctrl"]
    assert program.to_json() == CONTRACT
    assert FactorProgram.from_json(json.loads(json.dumps(program.to_json()))) == program


def test_optional_history_fields_round_trip() -> None:
    data = dict(
        CONTRACT,
        version=3,
        parent_version=2,
        rationale="why",
        edits=[{"operator": "Scale", "targets": ["r_vel"], "params": {"alpha": 0.5}, "justification": "j"}],
        diff="--- a\n+++ b\n",
    )
    data["factors"] = [dict(CONTRACT["factors"][0], polarity="reward", monotonicity="increasing in v_x")]
    program = FactorProgram.from_json(data)
    assert program.parent_version == 2 and program.edits[0]["operator"] == "Scale"
    assert program.factors[0].polarity == "reward"
    assert program.to_json() == data


def _with_factor(**changes: object) -> dict[str, object]:
    factor = dict(CONTRACT["factors"][0], **changes)  # type: ignore[arg-type]
    return dict(CONTRACT, factors=[factor])


@pytest.mark.parametrize(
    "data,fragment",
    [
        ([], "expected a JSON object"),
        ({"task": "halfcheetah", "version": 0}, "missing required field 'factors'"),
        (dict(CONTRACT, version=-1), "version"),
        (dict(CONTRACT, version="0"), "version"),
        (dict(CONTRACT, factors={}), "must be a list"),
        (dict(CONTRACT, factors=[]), "no factors"),
        (dict(CONTRACT, extra=1), "unknown field"),
        (_with_factor(name="r vel"), "not a valid identifier"),
        (_with_factor(name="_hidden"), "not a valid identifier"),
        (_with_factor(name="class"), "not a valid identifier"),
        (_with_factor(type="phi2"), "unknown"),
        (_with_factor(code=""), "empty"),
        (_with_factor(code=3), "must be a string"),
        (_with_factor(color="red"), "unknown field"),
        (_with_factor(polarity="up"), "polarity"),
        (_with_factor(code="def r_vel(s, a):\n    return s.x_velocity\n"), "state-only"),
        (_with_factor(code="def r_vel(s):\n    return a[:, 0]\n"), "state-only"),
        (dict(CONTRACT, factors=[CONTRACT["factors"][0], CONTRACT["factors"][0]]), "duplicate factor name"),
    ],
)
def test_schema_violations_are_rejected(data: object, fragment: str) -> None:
    with pytest.raises(ProgramParseError, match=fragment):
        FactorProgram.from_json(data)


def test_phi_using_action_names_the_rule() -> None:
    with pytest.raises(ProgramParseError) as info:
        FactorProgram.from_json(_with_factor(code="def r_vel(s):\n    return a[:, 0]\n"))
    assert [v.rule for v in info.value.violations] == ["phi-action"]
    assert isinstance(info.value, UsageError)


def test_content_hash_is_stable_and_ignores_history() -> None:
    program = FactorProgram.from_json(CONTRACT)
    again = FactorProgram.from_json(json.loads(json.dumps(CONTRACT)))
    assert program.content_hash() == again.content_hash()
    assert len(program.content_hash()) == 64
    later = FactorProgram.from_json(dict(CONTRACT, version=7, parent_version=6, rationale="x"))
    assert later.content_hash() == program.content_hash()
    changed = FactorProgram.from_json(_with_factor(doc="another doc"))
    assert changed.content_hash() != program.content_hash()


def test_code_diff_is_a_unified_diff() -> None:
    old = FactorProgram.from_json(CONTRACT)
    new = FactorProgram.from_json(_with_factor(code="def r_vel(s):\n    return 2.0 * s.x_velocity\n"))
    new = FactorProgram(new.task, 1, new.factors, parent_version=0)
    diff = code_diff(old, new)
    assert diff.startswith("--- halfcheetah v0\n+++ halfcheetah v1\n")
    assert "-    return s.x_velocity" in diff and "+    return 2.0 * s.x_velocity" in diff
    assert code_diff(old, old) == ""


def test_save_and_load(tmp_path: Path) -> None:
    program = example_program("humanoidstandup", 1)
    path = tmp_path / "sub" / "program.json"
    save_program(program, path)
    assert load_program(path) == program
    assert not [p for p in path.parent.iterdir() if p.name != "program.json"]  # no temp files left


def test_load_errors_are_usage_errors(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="no such file"):
        load_program(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json", encoding="utf-8")
    with pytest.raises(UsageError, match="invalid JSON"):
        load_program(bad)


def test_examples_follow_the_paper() -> None:
    hc0, hc1 = example_program("halfcheetah", 0), example_program("halfcheetah", 1)
    assert [f.name for f in hc0.phi_factors] == ["r_vel", "r_upright", "r_stable"]
    assert [f.name for f in hc0.aux_factors] == ["r_ctrl"]
    assert hc1.names == hc0.names and hc1.parent_version == 0 and hc1.edits[0]["operator"] == "Gate"
    assert "np.tanh" in hc1.factor("r_vel").code and "s.pitch" in hc1.factor("r_vel").code
    hs0, hs1 = example_program("humanoidstandup", 0), example_program("humanoidstandup", 1)
    assert hs0.names == ["r_height", "r_survival", "r_stable", "r_ctrl"]
    assert hs1.names == [*hs0.names, "r_explore"] and hs1.factor("r_explore").type == "PHI"
    assert "0.55" in hs1.factor("r_explore").code
    with pytest.raises(UsageError, match="no example program"):
        example_program("halfcheetah", 9)


def test_factor_type_is_required() -> None:
    with pytest.raises(ProgramParseError, match="missing required field 'type'"):
        Factor.from_json({"name": "r", "code": "def r(s):\n    return s.x\n"})
