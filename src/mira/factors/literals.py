"""Reading literal numbers and NumPy attribute chains out of factor code's syntax tree.

Shared by the static checker and the guard analysis, which both need to know when a node is a
constant (an exponent, a divisor, a bound) without evaluating anything.
"""

from __future__ import annotations

import ast


def numeric_literal(node: ast.AST) -> float | int | None:
    """The value of ``3``, ``-2.5``, ``+1`` as a number; None for anything else (bools included)."""
    sign = 1
    while isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
        if isinstance(node.op, ast.USub):
            sign = -sign
        node = node.operand
    if isinstance(node, ast.Constant) and type(node.value) in (int, float):
        value = node.value
        assert isinstance(value, int | float)
        return sign * value
    return None


def int_literal(node: ast.AST) -> int | None:
    value = numeric_literal(node)
    return value if type(value) is int else None


def is_np_linalg(node: ast.AST) -> bool:
    return (
        isinstance(node, ast.Attribute)
        and node.attr == "linalg"
        and isinstance(node.value, ast.Name)
        and node.value.id == "np"
    )
