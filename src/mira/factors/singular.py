"""Divisions, logarithms and square roots whose argument reaches zero (or below) where the task can go.

The sandbox runs a factor on real states, but a random policy's states rarely reach the boundary where
an episode ends: Hopper's torso falls past its termination height only when a policy has learned to
stand first, so ``s.x_velocity / s.height_margin`` is finite on every sandbox state and infinite exactly
where a trained hopper falls. This check reads each such operation's argument and, when the argument is
an affine function of one task feature (``s.f``, ``s.f - c``, ``c * s.f``, ...), computes its interval
over the feature's values on the sandbox states *and* over the range the card declares for it
(``range = [lo, hi]``: the values it takes while an episode runs, its termination thresholds included).
A denominator whose interval contains 0, a logarithm's that reaches 0 or below, a square root's that
goes below 0, is an error naming the factor, the line, the operation and the feature's value there.
Arguments of any other form are left to the sandbox's numeric checks.
"""

from __future__ import annotations

import ast
from collections.abc import Mapping

import numpy as np

from mira.factors.violations import Violation

_LOGS = ("log", "log2", "log10")


def _affine(node: ast.expr) -> tuple[str, float, float] | None:
    """``(feature, a, b)`` with node = a·s.feature + b, or None for any other form."""
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "s":
        return node.attr, 1.0, 0.0
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        inner = _affine(node.operand)
        sign = -1.0 if isinstance(node.op, ast.USub) else 1.0
        return None if inner is None else (inner[0], sign * inner[1], sign * inner[2])
    if isinstance(node, ast.BinOp):
        left, right = node.left, node.right
        const_l = left.value if isinstance(left, ast.Constant) and isinstance(left.value, int | float) else None
        const_r = right.value if isinstance(right, ast.Constant) and isinstance(right.value, int | float) else None
        if isinstance(node.op, ast.Add | ast.Sub):
            sign = 1.0 if isinstance(node.op, ast.Add) else -1.0
            if const_r is not None and (inner := _affine(left)) is not None:
                return inner[0], inner[1], inner[2] + sign * float(const_r)
            if const_l is not None and (inner := _affine(right)) is not None:
                return inner[0], sign * inner[1], float(const_l) + sign * inner[2]
        if isinstance(node.op, ast.Mult):
            if const_l is not None and (inner := _affine(right)) is not None:
                return inner[0], float(const_l) * inner[1], float(const_l) * inner[2]
            if const_r is not None and (inner := _affine(left)) is not None:
                return inner[0], float(const_r) * inner[1], float(const_r) * inner[2]
    return None


def _arguments(tree: ast.AST) -> list[tuple[str, ast.expr, int]]:
    """``(operation, argument, line)`` of every division, logarithm and square root in the code."""
    found: list[tuple[str, ast.expr, int]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div | ast.FloorDiv | ast.Mod):
            found.append(("division by", node.right, node.lineno))
        elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.args
              and isinstance(node.func.value, ast.Name) and node.func.value.id in ("np", "math")):
            if node.func.attr in _LOGS:
                found.append((f"{node.func.value.id}.{node.func.attr} of", node.args[0], node.lineno))
            elif node.func.attr == "sqrt":
                found.append((f"{node.func.value.id}.sqrt of", node.args[0], node.lineno))
    return found


def singular_operations(factor: str, code: str, values: Mapping[str, np.ndarray],
                        declared: Mapping[str, tuple[float, float]]) -> list[Violation]:
    """Errors for the operations of ``code`` whose argument reaches a singular value over the features'
    ``values`` (on the sandbox's states) and ``declared`` ranges (the card's)."""
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return []  # the static check reports it
    out: list[Violation] = []
    for op, arg, line in _arguments(tree):
        form = _affine(arg)
        if form is None:
            continue
        feature, a, b = form
        seen = np.asarray(values.get(feature, np.zeros(0)), dtype=np.float64)
        points = [float(v) for v in (seen.min(), seen.max())] if seen.size else []
        points += list(declared.get(feature, ()))
        if not points:
            continue
        lo_f, hi_f = min(points), max(points)
        lo, hi = sorted((a * lo_f + b, a * hi_f + b))
        text = ast.unparse(arg)
        where = f"{feature} in [{lo_f:.4g}, {hi_f:.4g}]" + (" (the card's range and the sandbox states)"
                                                             if feature in declared else " (the sandbox states)")
        if op == "division by" and lo <= 0.0 <= hi and a != 0.0:
            zero = -b / a + 0.0  # never "-0"
            out.append(Violation(factor, "singular", line, f"{op} {text}, which is 0 where {feature} = {zero:.4g}; "
                                                          f"{where}"))
        elif "log" in op and lo <= 0.0:
            out.append(Violation(factor, "singular", line, f"{op} {text}, which reaches {lo:.4g} (<= 0); {where}"))
        elif "sqrt" in op and lo < 0.0:
            out.append(Violation(factor, "singular", line, f"{op} {text}, which reaches {lo:.4g} (< 0); {where}"))
    return out
