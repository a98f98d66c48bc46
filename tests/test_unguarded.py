"""The static "unguarded" rule: divisions, logarithms and square roots of state- or action-dependent values
must carry a guard the code itself proves, whether or not the card declares a range for the feature."""

from __future__ import annotations

import pytest

from mira.factors.checker import check_code, check_program
from mira.factors.examples import example_program, example_programs
from mira.factors.program import FactorProgram
from mira.factors.violations import RULES
from mira.tasks.card import load_task

FEATURES = ["x", "h", "x_velocity", "height_margin"]


def _unguarded(code: str, kind: str = "PHI") -> list[str]:
    """Messages of the unguarded violations of ``code``; every other rule must hold."""
    found = check_code("f", kind, code, FEATURES)
    assert all(v.rule == "unguarded" for v in found), found
    return [f"{v.line}: {v.message}" for v in found]


def test_the_rule_is_documented() -> None:
    assert "unguarded" in RULES


def test_a_division_by_a_margin_is_refused_on_a_card_without_its_range() -> None:
    card = load_task("hopper")
    assert "height_margin" in card.feature_names
    code = "def r_x(s):\n    v = s.x_velocity\n    return v / s.height_margin\n"
    program = FactorProgram.from_json(
        {
            "task": "hopper",
            "version": 0,
            "factors": [{"name": "r_x", "type": "PHI", "code": code, "doc": "d", "units": "1",
                         "range_hint": "[-10, 10]"}],
        }
    )
    report = check_program(program, card)
    (violation,) = report.errors
    assert (violation.factor, violation.rule, violation.line, violation.severity) == ("r_x", "unguarded", 3, "error")
    assert violation.message.startswith("division by s.height_margin, which nothing keeps away from 0")
    assert "np.maximum(s.height_margin, 1e-3)" in violation.message  # the guard to write


@pytest.mark.parametrize(
    "body",
    [
        "return s.x / np.maximum(s.h, 0.05)",
        "return s.x / (abs(s.h) + 0.1)",
        "return s.x / (np.abs(s.h) + 0.1)",
        "return s.x / (1.0 + s.h ** 2)",
        "return s.x / (0.1 + np.square(s.h))",
        "d = np.maximum(s.h, 0.05)\n    return s.x / d",
        "d = abs(s.h) + 0.1\n    e = 2.0 * d\n    return s.x / e",
        "return s.x / 2.0",
        "return s.x / -(abs(s.h) + 1.0)",
        "return s.x / np.clip(s.h, 0.1, 5.0)",
        "return s.x / max(s.h, 0.1)",
        "return s.x / np.where(s.h > 0, s.h ** 2 + 1.0, 1.0)",
        "return s.x / np.cosh(s.h)",
        "return s.x / np.hypot(s.h, 0.5)",
        "return s.x % 3.0",
        "return np.log(np.exp(s.x) + 1)",
        "return np.log1p(s.x ** 2)",
        "return np.sqrt(s.x ** 2)",
        "return np.sqrt(np.abs(s.x))",
        "return np.sqrt(np.maximum(s.x, 0.0))",
        "return 1.0 / 0.0 + s.x",  # constant arithmetic is not this rule's business
    ],
)
def test_guarded_forms_are_admitted(body: str) -> None:
    assert _unguarded(f"def f(s):\n    {body}\n") == []


@pytest.mark.parametrize(
    ("body", "operation"),
    [
        ("return s.x / s.h", "division by s.h"),
        ("return s.x // (s.h + 2.0)", "floor division by s.h + 2.0"),
        ("return s.x % s.h", "remainder modulo s.h"),
        ("return s.h ** -1", "negative power of s.h"),
        ("return s.x / np.maximum(s.h, -1)", "division by np.maximum(s.h, -1)"),
        ("return s.x / np.maximum(s.h, 0.0)", "division by np.maximum(s.h, 0.0)"),
        ("return s.x / np.abs(s.h)", "division by np.abs(s.h)"),
        ("d = s.h\n    return s.x / d", "division by d"),
        ("d = 1.0\n    if s.h > 0:\n        d = 0.0\n    return s.x / d", "division by d"),
        ("t = s.x\n    t /= s.h\n    return t", "division by s.h"),
        ("return np.log(s.x)", "np.log of s.x"),
        ("return np.log(np.exp(s.x))", "np.log of np.exp(s.x)"),
        ("return np.log10(s.x + 1.0)", "np.log10 of s.x + 1.0"),
        ("return np.log1p(s.x)", "np.log1p of s.x"),
        ("return np.sqrt(s.x)", "np.sqrt of s.x"),
        ("return np.sqrt(s.x ** 2 - 1.0)", "np.sqrt of s.x ** 2 - 1.0"),
    ],
)
def test_unguarded_forms_are_refused(body: str, operation: str) -> None:
    (message,) = _unguarded(f"def f(s):\n    {body}\n")
    assert operation in message


def test_the_action_counts_and_the_message_names_line_and_guard() -> None:
    code = "def f(s, a):\n    n = np.linalg.norm(a, axis=-1)\n    return s.x / n\n"
    (message,) = _unguarded(code, "AUX")
    assert message.startswith("3: division by n, which nothing keeps away from 0: write np.maximum(n, 1e-3)")
    assert _unguarded("def f(s, a):\n    return s.x / (np.linalg.norm(a, axis=-1) + 1e-6)\n", "AUX") == []
    (log,) = _unguarded("def f(s):\n    return np.log(s.x)\n")
    assert "np.log(np.maximum(s.x, 1e-6))" in log
    (root,) = _unguarded("def f(s):\n    return np.sqrt(s.x)\n")
    assert "np.sqrt(np.maximum(s.x, 0.0))" in root


def test_shipped_examples_stay_admissible() -> None:
    for task, version in example_programs():
        report = check_program(example_program(task, version), load_task(task, check_env=False))
        assert not [v for v in report.violations if v.rule == "unguarded"], (task, version)


def test_long_chains_of_locals_are_checked_without_recursing_too_deep() -> None:
    lines = ["def f(s):", "    x0 = np.abs(s.h) + 1.0"] + [f"    x{i + 1} = 0.5 * x{i} + 1.0" for i in range(40)]
    assert _unguarded("\n".join([*lines, "    return s.x / x40", ""])) == []
    lines = ["def f(s):", "    x0 = s.h"] + [f"    x{i + 1} = x{i} + 1.0" for i in range(150)]
    assert _unguarded("\n".join([*lines, "    return s.x / x150", ""]))  # unknown beyond the depth bound: refused
