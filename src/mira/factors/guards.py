"""Divisions, logarithms and square roots that the code itself must keep inside their domain.

The sandbox sees the states a random policy visits and :mod:`.singular` the ranges a card declares;
neither sees where a *trained* policy goes (a hopper that learned to stand falls to exactly its
termination height). So a division, logarithm or square root of anything the state or action reaches
must carry its guard in the code, where it holds for every state: the argument's interval is proved
from the syntax alone (a small, conservative interval analysis), and what cannot be proved is refused
with the guard to write (rule ``unguarded``).
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

from mira.factors.literals import is_np_linalg, numeric_literal
from mira.factors.violations import Violation
from mira.factors.whitelist import MATH_CONSTANTS, NUMPY_CONSTANTS

Interval = tuple[float, float]
_UNKNOWN: Interval = (-math.inf, math.inf)
_MAX_INTERVAL_DEPTH = 200  # nested expressions and locals resolved through one another; deeper is unknown

#: ``np.<f>``/``math.<f>`` that divide: the position of the divisor and the operation's wording.
_DIVIDING_CALLS: dict[str, tuple[int, str]] = {
    "divide": (1, "division by"),
    "true_divide": (1, "division by"),
    "floor_divide": (1, "floor division by"),
    "mod": (1, "remainder modulo"),
    "remainder": (1, "remainder modulo"),
    "fmod": (1, "remainder modulo"),
    "reciprocal": (0, "reciprocal of"),
}
_DIVIDING_OPS: dict[type[ast.operator], str] = {
    ast.Div: "division by",
    ast.FloorDiv: "floor division by",
    ast.Mod: "remainder modulo",
}
_LOGS = frozenset({"log", "log2", "log10"})

#: Non-decreasing functions: the interval of f(x) is f of the argument's end points.
_MONOTONE: dict[str, Callable[[float], float]] = {
    "exp": math.exp,
    "exp2": lambda x: 2.0**x,
    "expm1": math.expm1,
    "log": math.log,
    "log2": math.log2,
    "log10": math.log10,
    "log1p": math.log1p,
    "sinh": math.sinh,
    "arcsinh": math.asinh,
    "tanh": math.tanh,
    "arctan": math.atan,
    "cbrt": lambda x: math.copysign(abs(x) ** (1.0 / 3.0), x),
    "floor": math.floor,
    "ceil": math.ceil,
    "rint": round,
    "trunc": math.trunc,
    "deg2rad": math.radians,
    "rad2deg": math.degrees,
    "float": float,
}
#: Functions whose values lie in a fixed interval whatever their arguments.
_FIXED: dict[str, Interval] = {
    "sin": (-1.0, 1.0),
    "cos": (-1.0, 1.0),
    "sign": (-1.0, 1.0),
    "arcsin": (-math.pi / 2, math.pi / 2),
    "arccos": (0.0, math.pi),
    "arccosh": (0.0, math.inf),
    "arctan2": (-math.pi, math.pi),
    "isfinite": (0.0, 1.0),
    "logical_not": (0.0, 1.0),
    "logical_and": (0.0, 1.0),
    "logical_or": (0.0, 1.0),
    "logical_xor": (0.0, 1.0),
    "std": (0.0, math.inf),
    "var": (0.0, math.inf),
    "norm": (0.0, math.inf),
    "ones_like": (1.0, 1.0),
    "zeros_like": (0.0, 0.0),
}


def _apply(fn: Callable[[float], float], x: float, default: float) -> float:
    """``fn(x)`` as a float; ``default`` where it overflows or is undefined (the end point stays unknown)."""
    try:
        value = float(fn(x))
    except (OverflowError, ValueError, ZeroDivisionError):
        return default
    return default if math.isnan(value) else value


def _times(p: Interval, q: Interval) -> Interval:
    """Interval product, with 0 * inf = 0 (an exact 0 end point times any finite value is 0)."""
    products = [0.0 if x == 0.0 or y == 0.0 else x * y for x in p for y in q]
    return min(products), max(products)


def _hull(*items: Interval) -> Interval:
    return min(i[0] for i in items), max(i[1] for i in items)


def _magnitude(p: Interval) -> Interval:
    """The interval of ``abs(x)`` for x in p."""
    lo, hi = p
    if lo >= 0.0:
        return p
    if hi <= 0.0:
        return -hi, -lo
    return 0.0, max(-lo, hi)


def _power(p: Interval, exponent: float) -> Interval:
    """The interval of ``x ** exponent`` for a literal exponent."""
    if exponent == 0:
        return 1.0, 1.0
    if exponent != int(exponent):
        return _UNKNOWN
    n = int(exponent)
    if n < 0:
        return (0.0, math.inf) if n % 2 == 0 else _UNKNOWN
    if n % 2 == 0:
        p = _magnitude(p)
    ends = [_apply(lambda x: x**n, v, math.copysign(math.inf, v)) for v in p]
    return min(ends), max(ends)


def _away_from_zero(p: Interval) -> bool:
    return p[0] > 0.0 or p[1] < 0.0


@dataclass
class _GuardAnalysis:
    """Finds the divisions, logarithms and square roots of state- or action-dependent values whose argument
    the code does not provably keep inside the operation's domain."""

    factor: str
    single: dict[str, ast.expr] = field(default_factory=dict)  # locals assigned exactly once
    dependent: set[str] = field(default_factory=set)  # locals that depend on s or a
    memo: dict[str, Interval] = field(default_factory=dict)
    resolving: set[str] = field(default_factory=set)

    def run(self, body: Sequence[ast.stmt]) -> list[Violation]:
        self._locals(body)
        out: list[Violation] = []
        for stmt in body:
            for node in ast.walk(stmt):
                for kind, op, arg in _singular_arguments(node):
                    if not self.depends(arg):
                        continue  # constant arithmetic: not a question of where the task goes
                    message = _unguarded_message(kind, op, arg, self.interval(arg, 0))
                    if message is not None:
                        line = int(getattr(node, "lineno", 0) or 0)
                        out.append(Violation(self.factor, "unguarded", line, message))
        return out

    def _locals(self, body: Sequence[ast.stmt]) -> None:
        """Which locals are assigned exactly once (by ``=``: their value is that expression) and which depend
        on ``s``/``a``, by data or through an ``if`` on them (a fixed point over every assignment)."""
        writes: list[tuple[str, list[ast.expr]]] = []  # name, the value and enclosing tests it depends on
        counts: dict[str, int] = {}
        values: dict[str, ast.expr] = {}

        def write(target: ast.AST, value: ast.expr | None, tests: list[ast.expr], times: int = 1) -> None:
            if isinstance(target, ast.Name):
                counts[target.id] = counts.get(target.id, 0) + times
                writes.append((target.id, [*tests, *([value] if value is not None else [])]))
                if value is not None:
                    values.setdefault(target.id, value)

        def visit(stmts: Sequence[ast.stmt], tests: list[ast.expr]) -> None:
            for stmt in stmts:
                if isinstance(stmt, ast.Assign):
                    for target in stmt.targets:
                        if not isinstance(target, ast.Tuple):
                            write(target, stmt.value, tests)
                        elif isinstance(stmt.value, ast.Tuple) and len(stmt.value.elts) == len(target.elts):
                            for elt, value in zip(target.elts, stmt.value.elts, strict=True):
                                write(elt, value, tests)
                        else:
                            for elt in target.elts:
                                write(elt, stmt.value, tests, times=2)
                elif isinstance(stmt, ast.AugAssign):
                    write(stmt.target, stmt.value, tests, times=2)  # x op= v: a second value of x
                elif isinstance(stmt, ast.For):
                    write(stmt.target, None, tests, times=2)
                    visit(stmt.body, tests)
                    visit(stmt.orelse, tests)
                elif isinstance(stmt, ast.If):
                    visit(stmt.body, [*tests, stmt.test])
                    visit(stmt.orelse, [*tests, stmt.test])

        visit(body, [])
        self.single = {name: value for name, value in values.items() if counts.get(name) == 1}
        changed = True
        while changed:
            changed = False
            for name, sources in writes:
                if name not in self.dependent and any(self.depends(e) for e in sources):
                    self.dependent.add(name)
                    changed = True

    def depends(self, node: ast.AST) -> bool:
        """Whether ``node`` reads the state or the action, directly or through a local."""
        return any(
            isinstance(sub, ast.Name) and (sub.id in ("s", "a") or sub.id in self.dependent)
            for sub in ast.walk(node)
        )

    # -- the interval of an expression
    def interval(self, node: ast.AST, depth: int) -> Interval:
        """An interval that provably holds every (non-NaN) value of ``node``; an unknown end is infinite."""
        if depth > _MAX_INTERVAL_DEPTH:
            return _UNKNOWN
        value = numeric_literal(node)
        if value is not None:
            return float(value), float(value)
        if isinstance(node, ast.Constant) and isinstance(node.value, bool):
            return float(node.value), float(node.value)
        if isinstance(node, ast.Name):
            return self._name(node.id, depth)
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
            table = {"np": NUMPY_CONSTANTS, "math": MATH_CONSTANTS}.get(node.value.id, {})
            return (table[node.attr], table[node.attr]) if node.attr in table else _UNKNOWN
        if isinstance(node, ast.Subscript):
            return self.interval(node.value, depth + 1)  # an element of x lies where x's elements lie
        if isinstance(node, ast.UnaryOp):
            inner = self.interval(node.operand, depth + 1)
            if isinstance(node.op, ast.USub):
                return -inner[1], -inner[0]
            return inner if isinstance(node.op, ast.UAdd) else _UNKNOWN
        if isinstance(node, ast.BinOp):
            return self._binop(node, depth)
        if isinstance(node, ast.IfExp):
            return _hull(self.interval(node.body, depth + 1), self.interval(node.orelse, depth + 1))
        if isinstance(node, ast.BoolOp):
            return _hull(*(self.interval(v, depth + 1) for v in node.values))
        if isinstance(node, ast.Compare):
            return 0.0, 1.0
        if isinstance(node, ast.Call):
            return self._call(node, depth)
        return _UNKNOWN

    def _name(self, name: str, depth: int) -> Interval:
        """A local's interval is its single value's; a name assigned more than once (or a loop variable,
        an argument, a name in a cycle) is unknown."""
        if name in self.memo:
            return self.memo[name]
        value = self.single.get(name)
        if value is None or name in self.resolving:
            return _UNKNOWN
        self.resolving.add(name)
        try:
            result = self.interval(value, depth + 1)
        finally:
            self.resolving.discard(name)
        self.memo[name] = result
        return result

    def _binop(self, node: ast.BinOp, depth: int) -> Interval:
        left = self.interval(node.left, depth + 1)
        if isinstance(node.op, ast.Pow):
            exponent = numeric_literal(node.right)
            return _UNKNOWN if exponent is None else _power(left, float(exponent))
        right = self.interval(node.right, depth + 1)
        if isinstance(node.op, ast.Add):
            lo, hi = left[0] + right[0], left[1] + right[1]
        elif isinstance(node.op, ast.Sub):
            lo, hi = left[0] - right[1], left[1] - right[0]
        elif isinstance(node.op, ast.Mult):
            lo, hi = _times(left, right)
        elif isinstance(node.op, ast.Div) and _away_from_zero(right):
            lo, hi = _times(left, (1.0 / right[1], 1.0 / right[0]))
        elif isinstance(node.op, ast.Mod) and right[0] > 0.0:
            lo, hi = 0.0, right[1]  # the remainder takes the divisor's sign
        else:
            return _UNKNOWN
        return (-math.inf if math.isnan(lo) else lo), (math.inf if math.isnan(hi) else hi)

    def _call(self, node: ast.Call, depth: int) -> Interval:
        func = node.func
        if isinstance(func, ast.Name) and func.id in ("abs", "min", "max", "float"):
            name = {"min": "minimum", "max": "maximum"}.get(func.id, func.id)  # builtins take values, not axes
        elif isinstance(func, ast.Attribute) and (
            (isinstance(func.value, ast.Name) and func.value.id == "np") or is_np_linalg(func.value)
        ):
            name = func.attr
        else:
            return _UNKNOWN
        if name in _FIXED:
            return _FIXED[name]
        if not node.args or any(isinstance(arg, ast.Starred) for arg in node.args):
            return _UNKNOWN
        args = [self.interval(arg, depth + 1) for arg in node.args]
        x = args[0]
        if name in ("abs", "absolute", "fabs"):
            return _magnitude(x)
        if name == "square":
            return _power(x, 2)
        if name == "sqrt":
            return _apply(math.sqrt, max(x[0], 0.0), 0.0), _apply(math.sqrt, max(x[1], 0.0), math.inf)
        if name == "cosh":
            mag = _magnitude(x)
            return _apply(math.cosh, mag[0], 1.0), _apply(math.cosh, mag[1], math.inf)
        if name == "hypot" and len(args) == 2:
            return max(_magnitude(args[0])[0], _magnitude(args[1])[0]), math.inf
        if name in _MONOTONE and len(node.args) == 1 and not node.keywords:
            fn = _MONOTONE[name]
            return _apply(fn, x[0], -math.inf), _apply(fn, x[1], math.inf)
        if name in ("maximum", "fmax") and len(args) >= 2:
            return max(a[0] for a in args), max(a[1] for a in args)
        if name in ("minimum", "fmin") and len(args) >= 2:
            return min(a[0] for a in args), min(a[1] for a in args)
        if name in ("max", "min", "amax", "amin", "mean"):
            return x  # a reduction's value is one of (or the mean of) the elements
        if name in ("sum", "prod") and x[0] >= 0.0:
            return 0.0, math.inf
        if name == "clip" and len(args) == 3:  # np.clip(x, lo, hi) == np.minimum(np.maximum(x, lo), hi)
            return min(max(x[0], args[1][0]), args[2][0]), min(max(x[1], args[1][1]), args[2][1])
        if name == "where" and len(args) == 3:
            return _hull(args[1], args[2])
        if name == "full_like" and len(args) == 2:
            return args[1]
        if name == "logaddexp" and len(args) == 2:
            return max(args[0][0], args[1][0]), max(args[0][1], args[1][1]) + math.log(2.0)
        if name == "heaviside" and len(args) == 2:
            return min(0.0, args[1][0]), max(1.0, args[1][1])
        if name == "power" and len(args) == 2 and (exponent := numeric_literal(node.args[1])) is not None:
            return _power(x, float(exponent))
        return _UNKNOWN


def _singular_arguments(node: ast.AST) -> list[tuple[str, str, ast.expr]]:
    """``(kind, operation, argument)`` of the singular operation ``node`` is, if any; kind is "divide",
    "log", "log1p" or "sqrt"."""
    if isinstance(node, ast.BinOp | ast.AugAssign):
        right = node.right if isinstance(node, ast.BinOp) else node.value
        left = node.left if isinstance(node, ast.BinOp) else node.target
        op = _DIVIDING_OPS.get(type(node.op))
        if op is not None:
            return [("divide", op, right)]
        if isinstance(node.op, ast.Pow) and (p := numeric_literal(right)) is not None and p < 0:
            return [("divide", "negative power of", left)]
        return []
    if not (
        isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and isinstance(node.func.value, ast.Name)
        and node.func.value.id in ("np", "math")
        and node.args
    ):
        return []
    attr, label = node.func.attr, f"{node.func.value.id}.{node.func.attr}"
    if attr in _DIVIDING_CALLS and len(node.args) > _DIVIDING_CALLS[attr][0]:
        index, op = _DIVIDING_CALLS[attr]
        return [("divide", f"{label}: {op}", node.args[index])]
    if attr in _LOGS or attr == "sqrt":
        return [("log" if attr in _LOGS else "sqrt", label, node.args[0])]
    if attr == "log1p":
        return [("log1p", label, node.args[0])]
    if attr == "power" and len(node.args) == 2 and (p := numeric_literal(node.args[1])) is not None and p < 0:
        return [("divide", f"{label}: negative power of", node.args[0])]
    return []


def _unguarded_message(kind: str, op: str, arg: ast.expr, bounds: Interval) -> str | None:
    """What is wrong with ``op`` applied to ``arg`` whose values lie in ``bounds``, and the guard to write;
    None when the bounds keep it in the operation's domain."""
    text = ast.unparse(arg)
    anywhere = "wherever the task goes (a trained policy reaches states the sandbox never saw)"
    if kind == "divide":
        if _away_from_zero(bounds):
            return None
        return (
            f"{op} {text}, which nothing keeps away from 0: write np.maximum({text}, 1e-3) "
            f"(or abs(x) + c, c + x ** 2 with c > 0) so it cannot be 0 {anywhere}"
        )
    if kind == "log":
        if bounds[0] > 0.0:
            return None
        return (
            f"{op} of {text}, which nothing keeps above 0: write {op}(np.maximum({text}, 1e-6)) "
            f"(or {op}(abs(x) + c), {op}(c + x ** 2) with c > 0) so it cannot reach 0 {anywhere}"
        )
    if kind == "log1p":
        if bounds[0] > -1.0:
            return None
        return (
            f"{op} of {text}, which nothing keeps above -1: write {op}(np.maximum({text}, -0.999)) "
            f"(or {op}(abs(x))) so it cannot reach -1 {anywhere}"
        )
    if bounds[0] >= 0.0:
        return None
    return (
        f"{op} of {text}, which nothing keeps at or above 0: write {op}(np.maximum({text}, 0.0)) "
        f"(or {op}(abs(x)), {op}(c + x ** 2)) so it cannot go below 0 {anywhere}"
    )


def unguarded_operations(factor: str, body: Sequence[ast.stmt]) -> list[Violation]:
    """Rule ``unguarded``: every division, logarithm or square root in a function ``body`` whose argument
    depends on ``s`` or ``a`` and is not provably inside the operation's domain."""
    return _GuardAnalysis(factor).run(body)
