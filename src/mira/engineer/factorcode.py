"""Writing and rewriting factor code for the offline engineer, as text in the factor-program contract.

The offline engineer must produce code that the factor checker admits (``s.<feature>``, ``a``,
arithmetic and a few ``np.`` functions; no strings, imports, comprehensions or loops), formatted
the same way every time so that equal inputs give byte-identical replies. Expressions therefore go
through Python's own ``ast`` (parse, transform, unparse) instead of string pasting: that normalises
spacing and parentheses, and wraps *every* ``return`` of an existing factor when it is gated,
clipped or scaled. Nothing here executes factor code.
"""

from __future__ import annotations

import ast
import math
import re
from collections.abc import Callable
from typing import Any

_RANGE = re.compile(r"^\s*[\[(]\s*([^,\s]+)\s*,\s*([^\])\s]+)\s*[\])]\s*$")


def num(value: float) -> str:
    """A float literal for code and params: rounded to 6 significant decimals, never ``-0.0``."""
    x = round(float(value), 6)
    if x == 0.0:
        x = 0.0
    return repr(x)


def normalise_expr(expr: str) -> str:
    """Canonical spelling of an expression (raises ``SyntaxError`` if it does not parse)."""
    return ast.unparse(ast.parse(expr, mode="eval").body)


def factor_code(name: str, expr: str, *, uses_action: bool = False) -> str:
    """``def NAME(s):`` (or ``(s, a)``) returning ``expr``, 4-space indent, trailing newline."""
    args = "s, a" if uses_action else "s"
    return f"def {name}({args}):\n    return {normalise_expr(expr)}\n"


def make_factor(name: str, ftype: str, expr: str, *, doc: str, units: str, range_hint: str) -> dict[str, Any]:
    """A factor record in the DESIGN.md contract."""
    return {
        "name": name,
        "type": ftype,
        "code": factor_code(name, expr, uses_action=ftype == "AUX"),
        "doc": doc,
        "units": units,
        "range_hint": range_hint,
    }


def _function(tree: ast.Module) -> ast.FunctionDef:
    for node in tree.body:
        if isinstance(node, ast.FunctionDef):
            return node
    raise ValueError("factor code defines no function")


def rewrite_returns(code: str, wrap: Callable[[str], str], *, new_name: str | None = None) -> str:
    """Replace every ``return X`` in the factor's function by ``return wrap(X)``.

    ``wrap`` gets the unparsed ``X`` and returns a new expression text, e.g.
    ``lambda x: f"({x}) * (1.0 - np.tanh(2.0 * np.square(s.pitch)))"``.
    """
    tree = ast.parse(code)
    func = _function(tree)
    if new_name is not None:
        func.name = new_name
    count = 0
    for node in ast.walk(func):
        if isinstance(node, ast.Return) and node.value is not None:
            node.value = ast.parse(wrap(ast.unparse(node.value)), mode="eval").body
            count += 1
    if count == 0:
        raise ValueError("factor code has no return value to rewrite")
    return ast.unparse(tree) + "\n"


def first_return_expr(code: str) -> str | None:
    """The expression of the first ``return`` in the factor (None when there is none)."""
    try:
        func = _function(ast.parse(code))
    except (SyntaxError, ValueError):
        return None
    for node in ast.walk(func):
        if isinstance(node, ast.Return) and node.value is not None:
            return ast.unparse(node.value)
    return None


def features_used(code: str) -> list[str]:
    """Names read as ``s.<name>`` by the code, in order of first use (``obs`` included)."""
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return []
    seen: list[str] = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and node.value.id == "s"
            and node.attr not in seen
        ):
            seen.append(node.attr)
    return seen


def squared_features(code: str) -> list[str]:
    """Features that appear squared (``np.square(s.f)``, ``s.f ** 2`` or ``s.f * s.f``)."""
    try:
        tree = ast.parse(code)
    except SyntaxError:
        return []

    def feat(node: ast.AST) -> str | None:
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "s":
            return node.attr
        return None

    out: list[str] = []
    for node in ast.walk(tree):
        name: str | None = None
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "square"
            and node.args
        ):
            name = feat(node.args[0])
        elif isinstance(node, ast.BinOp) and isinstance(node.op, ast.Pow):
            name = feat(node.left)
        elif isinstance(node, ast.BinOp) and isinstance(node.op, ast.Mult):
            left, right = feat(node.left), feat(node.right)
            name = left if left is not None and left == right else None
        if name is not None and name not in out:
            out.append(name)
    return out


def parse_range(hint: Any) -> tuple[float, float] | None:
    """``"[-15, 15]"`` → ``(-15.0, 15.0)``; None when absent or not two finite ordered numbers."""
    if isinstance(hint, list | tuple) and len(hint) == 2:
        parts = [str(hint[0]), str(hint[1])]
    elif isinstance(hint, str) and (m := _RANGE.match(hint)):
        parts = [m.group(1), m.group(2)]
    else:
        return None
    try:
        lo, hi = float(parts[0]), float(parts[1])
    except ValueError:
        return None
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        return None
    return lo, hi


def format_range(lo: float, hi: float) -> str:
    return f"[{_short_num(lo)}, {_short_num(hi)}]"


def _short_num(x: float) -> str:
    x = round(float(x), 6)
    if x == 0.0:
        return "0"
    return str(int(x)) if x == int(x) else repr(x)
