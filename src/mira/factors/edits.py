"""The admissible edit space of section 4.4.1.

Each operator maps a well-typed program to another well-typed program:

* ``Scale(f, alpha)``            f -> alpha * f
* ``Sat(f, lo, hi, mode)``       f -> clip(f, lo, hi)  (``mode="clip"``), or the smooth
                                 ``mid + half * tanh((f - mid) / half)``  (``mode="tanh"``)
* ``Gate(f, g)``                 f -> f * clip(g, 0, 1); g is a state predicate for PHI factors
                                 (``g(s)``); only AUX factors may use ``g(s, a)``
* ``Refactor(f, code)``          f's code replaced by an equivalent, loophole-averse rewrite
* ``Add(factor)``                a new documented factor (PHI if state-only, else AUX)
* ``Prune(f)``                   f removed (never the last PHI factor: Φ needs an input)

Rewrites are done on the syntax tree, not on text: every ``return EXPR`` of the factor becomes
``return WRAP(EXPR)``. That handles any admissible body (several returns, branches, loops) and
emits nothing the checker does not already admit, so an edited admissible factor stays
admissible (the property tests check this on random edit sequences). The generated code is
re-checked anyway, and an edit that would route an action-dependent signal into a PHI factor is
refused with :class:`EditError`.

Edits have the JSON form of the paper's Appendix A::

    {"operator": "Gate", "targets": ["r_vel"],
     "params": {"gate": "1 - np.tanh(2.0 * s.pitch ** 2)"}, "justification": "..."}

``apply_edits`` returns a new program (version + 1, parent version, the edit records, the rationale
and the unified diff).
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, ClassVar

from mira.errors import UsageError
from mira.factors.checker import check_code, check_program, feature_names_of, parse_range_hint
from mira.factors.program import (
    FACTOR_FIELDS,
    Factor,
    FactorProgram,
    ProgramParseError,
    code_diff,
)
from mira.factors.syntax import STATE_ONLY_TYPES, reads_action
from mira.factors.violations import Violation

if TYPE_CHECKING:
    from mira.tasks.card import TaskCard

OPERATORS = ("Scale", "Sat", "Gate", "Refactor", "Add", "Prune")
_META_KEYS = ("doc", "units", "range_hint", "polarity", "monotonicity")
_GATE_NAMES = frozenset({"s", "np", "math", "abs", "min", "max", "float"})


class EditError(UsageError):
    """An edit is malformed, names a missing factor, or would produce an ill-typed program."""

    def __init__(self, message: str, violations: Iterable[Violation] = ()) -> None:
        self.violations = list(violations)
        super().__init__(message)


# --------------------------------------------------------------------------- code rewriting


def _number(x: float) -> ast.expr:
    return ast.parse(repr(float(x)), mode="eval").body


def _function(code: str, name: str) -> tuple[ast.Module, ast.FunctionDef]:
    tree = ast.parse(code, mode="exec")
    for stmt in tree.body:
        if isinstance(stmt, ast.FunctionDef) and stmt.name == name:
            return tree, stmt
    raise EditError(f"factor {name!r}: its code has no function named {name!r}")


class _WrapReturns(ast.NodeTransformer):
    def __init__(self, wrap: Callable[[ast.expr], ast.expr]) -> None:
        self.wrap = wrap
        self.count = 0

    def visit_Return(self, node: ast.Return) -> ast.AST:
        if node.value is not None:
            node.value = self.wrap(node.value)
            self.count += 1
        return node


def rewrite_returns(code: str, name: str, wrap: Callable[[ast.expr], ast.expr]) -> str:
    """``code`` with every ``return EXPR`` of function ``name`` replaced by ``return wrap(EXPR)``."""
    tree, fn = _function(code, name)
    rewriter = _WrapReturns(wrap)
    fn.body = [rewriter.visit(stmt) for stmt in fn.body]
    if rewriter.count == 0:
        raise EditError(f"factor {name!r}: its code returns no value to rewrite")
    return ast.unparse(ast.fix_missing_locations(tree)) + "\n"


def _np_call(func: str, *args: ast.expr) -> ast.expr:
    return ast.Call(
        func=ast.Attribute(value=ast.Name(id="np", ctx=ast.Load()), attr=func, ctx=ast.Load()),
        args=list(args),
        keywords=[],
    )


def _mul(left: ast.expr, right: ast.expr) -> ast.expr:
    return ast.BinOp(left=left, op=ast.Mult(), right=right)


def gate_expression(gate: str, kind: str, target: str) -> ast.expr:
    """The predicate of a Gate as an expression over ``s`` (and ``a`` for AUX targets).

    Accepts a bare expression (``1 - np.tanh(2.0 * s.pitch ** 2)``) or a function whose body is a
    single ``return EXPR``. A PHI target's gate must be state-only.
    """
    if not isinstance(gate, str) or not gate.strip():
        raise EditError(f"Gate on {target!r}: the gate must be a non-empty code string")
    try:
        expr: ast.expr = ast.parse(gate.strip(), mode="eval").body
    except SyntaxError:
        try:
            tree = ast.parse(gate, mode="exec")
        except SyntaxError as exc:
            raise EditError(f"Gate on {target!r}: the gate does not parse ({exc.msg})") from None
        fns = [s for s in tree.body if isinstance(s, ast.FunctionDef)]
        if len(tree.body) != 1 or len(fns) != 1:
            raise EditError(
                f"Gate on {target!r}: give the gate as an expression or one def with one return"
            ) from None
        body = [s for s in fns[0].body if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant))]
        if len(body) != 1 or not isinstance(body[0], ast.Return) or body[0].value is None:
            raise EditError(f"Gate on {target!r}: a gate function must be a single 'return EXPR'") from None
        params = [p.arg for p in fns[0].args.args]
        if params not in (["s"], ["s", "a"]):
            raise EditError(f"Gate on {target!r}: a gate function takes (s) or (s, a)") from None
        expr = body[0].value
    allowed = _GATE_NAMES | ({"a"} if kind == "AUX" else set())
    for node in ast.walk(expr):
        if isinstance(node, ast.Name):
            if node.id == "a" and kind in STATE_ONLY_TYPES:
                raise EditError(
                    f"Gate on {target!r}: the gate reads the action 'a', which would route an "
                    f"action-dependent signal into a {kind} factor (a potential must be state-only; "
                    "gate with g(s), or gate an AUX factor)"
                )
            if node.id not in allowed:
                raise EditError(
                    f"Gate on {target!r}: the gate may only use s{', a' if kind == 'AUX' else ''}, np, "
                    f"math, abs, min, max, float (found {node.id!r})"
                )
    return expr


# --------------------------------------------------------------------------- operators


def _finite(value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise EditError(f"{what} must be a finite number, got {value!r}")
    if abs(value) > 1e9:
        raise EditError(f"{what} = {value!r} is out of range")
    return float(value)


def _meta(params: Mapping[str, Any]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in _META_KEYS:
        if key in params:
            value = params[key]
            if not (isinstance(value, str) or (value is None and key in ("polarity", "monotonicity"))):
                raise EditError(f"metadata {key!r} must be a string")
            out[key] = value
    return out


def _fmt_range(lo: float, hi: float) -> str:
    return f"[{lo + 0.0:.6g}, {hi + 0.0:.6g}]"  # + 0.0 turns -0.0 into 0.0


def _find(factors: Sequence[Factor], name: str, operator: str) -> int:
    for i, f in enumerate(factors):
        if f.name == name:
            return i
    raise EditError(
        f"{operator}: there is no factor named {name!r} (have: {', '.join(f.name for f in factors)})"
    )


def _admissible_source(factor: Factor, operator: str) -> None:
    errors = [v for v in check_code(factor.name, factor.type, factor.code) if v.is_error]
    if errors:
        raise EditError(
            f"{operator}: factor {factor.name!r} is not admissible, so it cannot be rewritten", errors
        )


@dataclass(frozen=True)
class Edit:
    """Base of the operators: a target, a justification, metadata overrides."""

    operator: ClassVar[str] = ""
    justification: str = field(default="", kw_only=True)
    metadata: Mapping[str, Any] = field(default_factory=dict, kw_only=True)

    @property
    def targets(self) -> list[str]:
        return [self.target] if hasattr(self, "target") else []

    def params(self) -> dict[str, Any]:
        return {}

    def to_json(self) -> dict[str, Any]:
        """The Appendix A record of this edit."""
        return {
            "operator": self.operator,
            "targets": self.targets,
            "params": {**self.params(), **dict(self.metadata)},
            "justification": self.justification,
        }

    def apply(self, factors: Sequence[Factor]) -> list[Factor]:
        raise NotImplementedError

    def _rewrite(
        self, factors: Sequence[Factor], target: str, wrap: Callable[[ast.expr], ast.expr], **meta: Any
    ) -> list[Factor]:
        out = list(factors)
        i = _find(out, target, self.operator)
        old = out[i]
        _admissible_source(old, self.operator)
        code = rewrite_returns(old.code, old.name, wrap)
        out[i] = replace(old, code=code, **{**meta, **_meta(self.metadata)})
        return out


@dataclass(frozen=True)
class Scale(Edit):
    """Replace f with alpha * f."""

    operator: ClassVar[str] = "Scale"
    target: str
    alpha: float

    def __post_init__(self) -> None:
        if _finite(self.alpha, "Scale alpha") == 0.0:
            raise EditError("Scale alpha must be non-zero (use Prune to remove a factor)")

    def params(self) -> dict[str, Any]:
        return {"alpha": self.alpha}

    def apply(self, factors: Sequence[Factor]) -> list[Factor]:
        alpha = float(self.alpha)
        old = factors[_find(factors, self.target, self.operator)]
        meta: dict[str, Any] = {}
        bounds = parse_range_hint(old.range_hint)
        if bounds is not None:
            lo, hi = sorted((alpha * bounds[0], alpha * bounds[1]))
            meta["range_hint"] = _fmt_range(lo, hi)
        if alpha < 0 and old.polarity in ("reward", "penalty"):
            meta["polarity"] = "penalty" if old.polarity == "reward" else "reward"
        return self._rewrite(factors, self.target, lambda e: _mul(_number(alpha), e), **meta)


@dataclass(frozen=True)
class Sat(Edit):
    """Bound f to [lo, hi]: hard clip, or the smooth tanh saturation with the same bounds."""

    operator: ClassVar[str] = "Sat"
    target: str
    lo: float
    hi: float
    mode: str = "clip"

    def __post_init__(self) -> None:
        lo, hi = _finite(self.lo, "Sat lo"), _finite(self.hi, "Sat hi")
        if not lo < hi:
            raise EditError(f"Sat needs lo < hi, got [{lo}, {hi}]")
        if self.mode not in ("clip", "tanh"):
            raise EditError(f"Sat mode must be 'clip' or 'tanh', got {self.mode!r}")

    def params(self) -> dict[str, Any]:
        return {"lo": self.lo, "hi": self.hi, "mode": self.mode}

    def apply(self, factors: Sequence[Factor]) -> list[Factor]:
        lo, hi = float(self.lo), float(self.hi)
        old = factors[_find(factors, self.target, self.operator)]
        bounds = parse_range_hint(old.range_hint)
        new_lo, new_hi = (max(lo, bounds[0]), min(hi, bounds[1])) if bounds else (lo, hi)
        if new_lo > new_hi:
            new_lo, new_hi = lo, hi
        if self.mode == "clip":

            def wrap(e: ast.expr) -> ast.expr:
                return _np_call("clip", e, _number(lo), _number(hi))
        else:
            mid, half = (lo + hi) / 2.0, (hi - lo) / 2.0

            def wrap(e: ast.expr) -> ast.expr:
                inner = e if mid == 0.0 else ast.BinOp(left=e, op=ast.Sub(), right=_number(mid))
                squashed = _mul(
                    _number(half), _np_call("tanh", ast.BinOp(left=inner, op=ast.Div(), right=_number(half)))
                )
                return squashed if mid == 0.0 else ast.BinOp(left=_number(mid), op=ast.Add(), right=squashed)

        return self._rewrite(factors, self.target, wrap, range_hint=_fmt_range(new_lo, new_hi))


@dataclass(frozen=True)
class Gate(Edit):
    """Multiply f by a predicate g in [0, 1] (clipped to it unless ``clip=False``)."""

    operator: ClassVar[str] = "Gate"
    target: str
    gate: str
    clip: bool = True

    def params(self) -> dict[str, Any]:
        return {"gate": self.gate, "clip": self.clip}

    def apply(self, factors: Sequence[Factor]) -> list[Factor]:
        old = factors[_find(factors, self.target, self.operator)]
        gate_expression(self.gate, old.type, old.name)  # refuse a bad or action-reading gate up front
        meta: dict[str, Any] = {}
        bounds = parse_range_hint(old.range_hint)
        if bounds is not None:
            meta["range_hint"] = _fmt_range(min(bounds[0], 0.0), max(bounds[1], 0.0))

        def wrap(e: ast.expr) -> ast.expr:
            g = gate_expression(self.gate, old.type, old.name)  # a fresh tree per return
            return _mul(e, _np_call("clip", g, _number(0.0), _number(1.0)) if self.clip else g)

        return self._rewrite(factors, self.target, wrap, **meta)


@dataclass(frozen=True)
class Refactor(Edit):
    """Replace f's code with an equivalent rewrite (same name, same type)."""

    operator: ClassVar[str] = "Refactor"
    target: str
    code: str

    def params(self) -> dict[str, Any]:
        return {"code": self.code}

    def apply(self, factors: Sequence[Factor]) -> list[Factor]:
        out = list(factors)
        i = _find(out, self.target, self.operator)
        old = out[i]
        if not isinstance(self.code, str) or not self.code.strip():
            raise EditError(f"Refactor of {self.target!r}: code must be a non-empty string")
        if old.type in STATE_ONLY_TYPES and reads_action(self.code):
            raise EditError(
                f"Refactor of {self.target!r}: the new code reads the action 'a', which would route an "
                f"action-dependent signal into a {old.type} factor"
            )
        code = self.code if self.code.endswith("\n") else self.code + "\n"
        out[i] = replace(old, code=code, **_meta(self.metadata))
        return out


@dataclass(frozen=True)
class Add(Edit):
    """Add a new, documented factor (PHI if state-only, else AUX)."""

    operator: ClassVar[str] = "Add"
    factor: Factor

    @property
    def targets(self) -> list[str]:
        return [self.factor.name]

    def params(self) -> dict[str, Any]:
        data = self.factor.to_json()
        data.pop("name")
        return data

    def apply(self, factors: Sequence[Factor]) -> list[Factor]:
        if any(f.name == self.factor.name for f in factors):
            raise EditError(f"Add: a factor named {self.factor.name!r} already exists")
        if self.factor.type in STATE_ONLY_TYPES and reads_action(self.factor.code):
            raise EditError(
                f"Add: {self.factor.name!r} reads the action 'a' but is typed {self.factor.type}; action-dependent "
                "signals may not feed a potential (type it AUX)"
            )
        return [*factors, self.factor]


@dataclass(frozen=True)
class Prune(Edit):
    """Remove a factor."""

    operator: ClassVar[str] = "Prune"
    target: str

    def apply(self, factors: Sequence[Factor]) -> list[Factor]:
        i = _find(factors, self.target, self.operator)
        out = [f for j, f in enumerate(factors) if j != i]
        if factors[i].type == "PHI" and not any(f.type == "PHI" for f in out):
            raise EditError(
                f"Prune: {self.target!r} is the last PHI factor; the potential needs at least one"
            )
        return out


# --------------------------------------------------------------------------- JSON form


_ALIASES: dict[str, tuple[str, ...]] = {
    "alpha": ("alpha", "scale", "factor"),
    "lo": ("lo", "low", "lower", "l", "min"),
    "hi": ("hi", "high", "upper", "u", "max"),
    "gate": ("gate", "predicate", "g", "g_code"),
}


def _param(params: Mapping[str, Any], key: str, operator: str) -> Any:
    for alias in _ALIASES.get(key, (key,)):
        if alias in params:
            return params[alias]
    raise EditError(f"{operator}: params need {key!r}")


def edit_from_json(record: Any) -> list[Edit]:
    """The Edit objects of one Appendix A record (one per target); raises :class:`EditError`."""
    if not isinstance(record, Mapping):
        raise EditError(f"an edit must be a JSON object, got {type(record).__name__}")
    unknown = sorted(set(record) - {"operator", "targets", "params", "justification"})
    if unknown:
        raise EditError(f"edit: unknown field(s) {', '.join(map(repr, unknown))}")
    operator = record.get("operator")
    if operator not in OPERATORS:
        raise EditError(f"edit: operator must be one of {', '.join(OPERATORS)}, got {operator!r}")
    targets = record.get("targets", [])
    if isinstance(targets, str):
        targets = [targets]
    if not isinstance(targets, list) or not all(isinstance(t, str) for t in targets):
        raise EditError(f"{operator}: targets must be a list of factor names")
    params = record.get("params", {})
    if not isinstance(params, Mapping):
        raise EditError(f"{operator}: params must be an object")
    justification = record.get("justification", "")
    if not isinstance(justification, str):
        raise EditError(f"{operator}: justification must be a string")
    meta = _meta(params)
    common: dict[str, Any] = {"justification": justification, "metadata": meta}
    if operator == "Add":
        spec = params.get("factor", params)
        if not isinstance(spec, Mapping):
            raise EditError("Add: params.factor must be an object")
        data = {k: v for k, v in spec.items() if k in FACTOR_FIELDS}
        if "name" not in data:
            if len(targets) != 1:
                raise EditError("Add: give the new factor's name as the single target or params.name")
            data["name"] = targets[0]
        try:
            factor = Factor.from_json(data, f"Add {data['name']!r}")
        except ProgramParseError as exc:
            message = str(exc)
            if "action" in message:
                message += " (an action-dependent signal may not be routed into PHI)"
            raise EditError(f"Add: {message}", exc.violations) from None
        return [Add(factor, justification=justification)]
    if not targets:
        raise EditError(f"{operator}: targets must name at least one factor")
    out: list[Edit] = []
    for target in targets:
        if operator == "Scale":
            out.append(Scale(target, _finite(_param(params, "alpha", operator), "Scale alpha"), **common))
        elif operator == "Sat":
            mode = params.get("mode", "tanh" if params.get("smooth") is True else "clip")
            out.append(
                Sat(
                    target,
                    _param(params, "lo", operator),
                    _param(params, "hi", operator),
                    str(mode),
                    **common,
                )
            )
        elif operator == "Gate":
            clip = params.get("clip", True)
            if not isinstance(clip, bool):
                raise EditError("Gate: clip must be true or false")
            out.append(Gate(target, _param(params, "gate", operator), clip, **common))
        elif operator == "Refactor":
            code = _param(params, "code", operator)
            out.append(Refactor(target, code, **common))
        else:
            out.append(Prune(target, justification=justification))
    return out


def _as_edits(edits: Iterable[Edit | Mapping[str, Any]]) -> list[Edit]:
    out: list[Edit] = []
    for e in edits:
        out.extend([e] if isinstance(e, Edit) else edit_from_json(e))
    return out


def apply_edit(program: FactorProgram, edit: Edit | Mapping[str, Any], **kwargs: Any) -> FactorProgram:
    """``apply_edits`` with a single edit."""
    return apply_edits(program, [edit], **kwargs)


def apply_edits(
    program: FactorProgram,
    edits: Iterable[Edit | Mapping[str, Any]],
    *,
    card: TaskCard | Sequence[str] | None = None,
    new_version: int | None = None,
    rationale: str | None = None,
) -> FactorProgram:
    """A new program version with the edits applied in order.

    The result has ``version = new_version or program.version + 1``, ``parent_version =
    program.version``, the edit records, a rationale (the justifications unless given) and the
    unified diff. It is statically checked (against ``card``'s features when given); any error, a
    missing target or an action routed into PHI raises :class:`EditError` and nothing changes.
    """
    parsed = _as_edits(edits)
    if not parsed:
        raise EditError("no edits to apply")
    factors: list[Factor] = list(program.factors)
    for edit in parsed:
        factors = edit.apply(factors)
    why = (
        rationale if rationale is not None else "; ".join(e.justification for e in parsed if e.justification)
    )
    try:
        new = FactorProgram(
            task=program.task,
            version=program.version + 1 if new_version is None else new_version,
            factors=tuple(factors),
            parent_version=program.version,
            edits=tuple(e.to_json() for e in parsed),
            rationale=why,
        )
    except ProgramParseError as exc:
        raise EditError(f"the edits give an invalid program: {exc}", exc.violations) from None
    features = None
    if card is not None:
        features = feature_names_of(card)
    report = check_program(new, features)
    if not report.ok:
        raise EditError("the edited program is not admissible: " + "; ".join(report.lines()), report.errors)
    return replace(new, diff=code_diff(program, new))
