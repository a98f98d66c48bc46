"""Static integrity of factor code (section 4.4.4, first stage) by an AST *whitelist*.

Factor code comes from an LLM and is treated as if an attacker wrote it. The checker therefore
never asks "is this construct dangerous?" but "is this construct one of the few the factor language
has?": every AST node type is handled explicitly and anything not handled is rejected, so a new
Python feature, an unusual spelling or a construct nobody thought of is refused by default.

What the language has (see ``whitelist.allowed_syntax_summary``): one ``def NAME(s)`` (PHI) or
``def NAME(s, a)`` (AUX); arithmetic, comparisons, boolean operators, conditional expressions; local
assignment (plain, augmented, tuple unpacking of a tuple of the same length); ``if``;
``for i in range(CONST)`` with a small constant bound and ``i`` used only as an index; ``return``;
numeric literals of bounded size; reads of ``s.<declared feature>``, ``s.obs`` and ``a``; calls of
``np.<whitelisted>``, ``np.linalg.norm``, ``abs``, ``min``, ``max``, ``float``.

Why each restriction exists:

* no imports, no dunder/underscore names, attribute access only on ``s`` and ``np``/``math``: these
  are the only routes from an expression to modules, frames, classes and builtins (``().__class__
  .__bases__[0].__subclasses__()`` and friends need an underscore attribute; ``eval``/``open``/
  ``getattr`` need a builtin name the namespace does not have);
* ``s`` may only be read as ``s.<feature>``: passing the view object itself to NumPy would build
  object arrays that compute with unbounded Python integers;
* no strings, lists, dicts, tuples as values, no ``not``: they are the remaining sources of Python
  objects whose size or magnitude is not bounded by the batch (``t = t + t`` doubles a tuple);
* integer literals only where NumPy needs an int (index, axis, ``range``, exponent); the compiler
  turns every other literal into a NumPy float64, so arithmetic never reaches Python's bignums;
* loops only over ``range(CONST)``, and a static operation bound (each node weighted by the
  iterations of its enclosing loops): together with "no function creates arrays larger than its
  inputs" this bounds a factor's cost by a constant times the batch size, *whatever the data*;
  so a branch the sandbox never took cannot hide a time bomb;
* ``s.<name>`` must be a feature the task card declares: there is no next state, no future
  quantity, no hidden simulator handle to read ("no future dependence");
* a PHI factor may not mention ``a``: it feeds the potential Φ(s), which must be state-only;
* a division, logarithm or square root of a value read from ``s`` or ``a`` must be guarded in the code
  ("unguarded"): a trained policy reaches states neither the sandbox nor the card's ranges show, so
  only a bound the code proves (``np.maximum(x, c)``, ``abs(x) + c``, ``c + x ** 2``) holds there.

Metadata (doc, units, range_hint) is required: a missing field is an *error* (the paper makes
documented units/range an admissibility constraint); a range_hint that does not read ``[lo, hi]``
is a *warning* (the hint is for people and prompts; the sandbox reports the observed range).
"""

from __future__ import annotations

import ast
import builtins
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from mira.factors.guards import unguarded_operations
from mira.factors.literals import int_literal, is_np_linalg, numeric_literal
from mira.factors.syntax import MAX_CODE_CHARS, STATE_ONLY_TYPES
from mira.factors.violations import Violation
from mira.factors.whitelist import (
    BUILTIN_FUNCTIONS,
    MATH_CONSTANTS,
    MAX_INT_LITERAL,
    MAX_POWER,
    NUMPY_CONSTANTS,
    NUMPY_FUNCTIONS,
    NUMPY_LINALG_FUNCTIONS,
    RESERVED_NAMES,
    ArgSpec,
)

if TYPE_CHECKING:
    from mira.factors.program import Factor, FactorProgram
    from mira.tasks.card import TaskCard

#: Limits that keep parsing, checking and running a factor cheap whatever its text.
MAX_NODES = 2000
MAX_DEPTH = 80
MAX_LOOP_ITERATIONS = 256  # one loop
MAX_TOTAL_ITERATIONS = 1024  # product over nested loops
MAX_COST = 4000  # expression nodes, each weighted by the iterations of its enclosing loops
MAX_FACTORS = 32

_PARAMS = {"PHI": ["s"], "AUX": ["s", "a"], "SHAPE": ["s"]}
_IMPORT_NAMES = frozenset({"__import__", "importlib", "import_module"})
_BUILTIN_NAMES = frozenset(dir(builtins))
_OK_BINOPS = (
    ast.Add,
    ast.Sub,
    ast.Mult,
    ast.Div,
    ast.FloorDiv,
    ast.Mod,
    ast.Pow,
    ast.BitAnd,
    ast.BitOr,
    ast.BitXor,
)
_OK_CMPOPS = (ast.Eq, ast.NotEq, ast.Lt, ast.LtE, ast.Gt, ast.GtE)
_OK_UNARY = (ast.USub, ast.UAdd, ast.Invert)


@dataclass(frozen=True)
class StaticReport:
    """Outcome of the static checks of a whole program: every violation, errors and warnings."""

    violations: tuple[Violation, ...] = ()

    @property
    def errors(self) -> list[Violation]:
        return [v for v in self.violations if v.is_error]

    @property
    def warnings(self) -> list[Violation]:
        return [v for v in self.violations if not v.is_error]

    @property
    def ok(self) -> bool:
        """True when nothing blocks admission (warnings do not)."""
        return not self.errors

    def lines(self) -> list[str]:
        return [str(v) for v in self.violations]


# --------------------------------------------------------------------------- helpers


def parse_range_hint(text: str) -> tuple[float, float] | None:
    """``"[lo, hi]"`` (brackets or parentheses, ``inf`` allowed) as numbers; None if it does not read so."""
    if not isinstance(text, str):
        return None
    m = re.fullmatch(r"\s*[\[(]\s*([^,\s]+)\s*,\s*([^\])\s]+)\s*[\])]\s*", text)
    if m is None:
        return None
    try:
        lo, hi = float(m.group(1)), float(m.group(2))
    except ValueError:
        return None
    if math.isnan(lo) or math.isnan(hi) or lo > hi:
        return None
    return lo, hi


def _inert_annotation(node: ast.AST | None) -> bool:
    """Annotations the compiler may drop unevaluated: names, dotted names, strings, None."""
    if node is None:
        return True
    if isinstance(node, ast.Name):
        return not node.id.startswith("_")
    if isinstance(node, ast.Attribute):
        return not node.attr.startswith("_") and _inert_annotation(node.value)
    return isinstance(node, ast.Constant) and (node.value is None or isinstance(node.value, str))


def _size_problem(tree: ast.AST) -> str | None:
    """Iteratively (so hostile nesting cannot exhaust the stack) count nodes and nesting depth."""
    count = 0
    stack: list[tuple[ast.AST, int]] = [(tree, 0)]
    while stack:
        node, depth = stack.pop()
        count += 1
        if count > MAX_NODES:
            return f"more than {MAX_NODES} syntax nodes"
        if depth > MAX_DEPTH:
            return f"nesting deeper than {MAX_DEPTH} levels"
        stack.extend((child, depth + 1) for child in ast.iter_child_nodes(node))
    return None


# --------------------------------------------------------------------------- the checker


@dataclass
class _FunctionChecker:
    """Walks one factor function; every node type it does not know is a violation."""

    factor: str
    kind: str
    features: frozenset[str] | None
    violations: list[Violation] = field(default_factory=list)
    locals_: set[str] = field(default_factory=set)
    loop_vars: set[str] = field(default_factory=set)
    cost: int = 0
    has_return: bool = False

    # -- reporting
    def fail(self, node: ast.AST | None, rule: str, message: str) -> None:
        line = int(getattr(node, "lineno", 0) or 0)
        self.violations.append(Violation(self.factor, rule, line, message))

    # -- entry
    def check_function(self, fn: ast.FunctionDef) -> None:
        if fn.name != self.factor:
            self.fail(fn, "signature", f"the function is named {fn.name!r}; it must be named {self.factor!r}")
        for dec in fn.decorator_list:
            self.fail(dec, "decorator", "decorators are not allowed")
        self._check_arguments(fn)
        if not _inert_annotation(fn.returns):
            self.fail(fn.returns, "annotation", "the return annotation must be a plain name")
        body = list(fn.body)
        if (
            body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            body = body[1:]  # docstring: inert, dropped by the compiler
        self._collect_locals(body)
        self._block(body, mult=1, in_loop=False)
        self.violations.extend(unguarded_operations(self.factor, body))
        if not self.has_return:
            self.fail(fn, "return", "the function never returns a value")
        if self.cost > MAX_COST:
            self.fail(fn, "size", f"static operation bound {self.cost} exceeds {MAX_COST} (loops multiply)")

    def _check_arguments(self, fn: ast.FunctionDef) -> None:
        args = fn.args
        if args.defaults or any(d is not None for d in args.kw_defaults):
            self.fail(fn, "default", "default argument values are not allowed")
        if args.posonlyargs or args.vararg or args.kwonlyargs or args.kwarg:
            self.fail(fn, "signature", "only plain positional parameters are allowed")
        names = [a.arg for a in args.args]
        expected = _PARAMS.get(self.kind)
        if expected is None:
            self.fail(fn, "signature", f"unknown factor type {self.kind!r}")
        elif names != expected:
            if self.kind in STATE_ONLY_TYPES and names == _PARAMS["AUX"]:
                self.fail(fn, "phi-action", f"a {self.kind} factor is state-only: its signature is (s), not (s, a)")
            else:
                self.fail(
                    fn,
                    "signature",
                    f"parameters are ({', '.join(names)}); a {self.kind} factor takes "
                    f"({', '.join(expected)})",
                )
        for arg in [*args.posonlyargs, *args.args, *args.kwonlyargs]:
            if not _inert_annotation(arg.annotation):
                self.fail(arg, "annotation", "parameter annotations must be plain names")

    def _collect_locals(self, body: Sequence[ast.stmt]) -> None:
        nodes = [node for stmt in body for node in ast.walk(stmt)]
        loop_targets = {id(node.target) for node in nodes if isinstance(node, ast.For)}
        for node in nodes:
            if isinstance(node, ast.For) and isinstance(node.target, ast.Name):
                self.loop_vars.add(node.target.id)
            elif (
                isinstance(node, ast.Name)
                and isinstance(node.ctx, ast.Store)
                and id(node) not in loop_targets
            ):
                self.locals_.add(node.id)

    # -- statements
    def _block(self, body: Sequence[ast.stmt], mult: int, in_loop: bool) -> None:
        for stmt in body:
            self._stmt(stmt, mult, in_loop)

    def _stmt(self, node: ast.stmt, mult: int, in_loop: bool) -> None:
        if isinstance(node, ast.Assign):
            self._assign(node, mult)
        elif isinstance(node, ast.AugAssign):
            self._store_name(node.target, loop_ok=False)
            self._binop_check(node, node.op, node.value)
            self._expr(node.value, mult)
        elif isinstance(node, ast.AnnAssign):
            self.fail(node, "annotation", "annotated assignments are not allowed")
        elif isinstance(node, ast.If):
            self._expr(node.test, mult)
            self._block(node.body, mult, in_loop)
            self._block(node.orelse, mult, in_loop)
        elif isinstance(node, ast.For):
            self._for(node, mult)
        elif isinstance(node, ast.Return):
            if node.value is None:
                self.fail(node, "return", "a bare return gives None; return an array")
            else:
                self.has_return = True
                self._expr(node.value, mult)
        elif isinstance(node, ast.Pass):
            pass
        elif isinstance(node, ast.Break | ast.Continue):
            if not in_loop:
                self.fail(node, "construct", f"{type(node).__name__.lower()} outside a loop")
        elif isinstance(node, ast.While):
            self.fail(node, "loop", "while loops are not allowed (use for i in range(CONST))")
        elif isinstance(node, ast.Import | ast.ImportFrom):
            self.fail(node, "import", "imports are not allowed")
        elif isinstance(node, ast.Global | ast.Nonlocal):
            self.fail(node, "global", f"{type(node).__name__.lower()} declarations are not allowed")
        elif isinstance(node, ast.Expr):
            if isinstance(node.value, ast.Constant) and isinstance(node.value.value, str | bytes):
                self.fail(node, "string", "string statements are only allowed as the docstring")
            else:
                self.fail(node, "construct", "expression statements have no effect in a pure factor")
                self._expr(node.value, mult)
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            self.fail(node, "construct", f"nested {type(node).__name__} is not allowed")
        else:
            self.fail(node, "construct", f"{type(node).__name__} statements are not allowed")

    def _assign(self, node: ast.Assign, mult: int) -> None:
        for target in node.targets:
            if isinstance(target, ast.Tuple):
                if not (
                    isinstance(node.value, ast.Tuple)
                    and len(node.value.elts) == len(target.elts)
                    and len(node.targets) == 1
                ):
                    self.fail(
                        node, "construct", "tuple unpacking needs a tuple of the same length on the right"
                    )
                for elt in target.elts:
                    self._store_name(elt, loop_ok=False)
            else:
                self._store_name(target, loop_ok=False)
        if (
            isinstance(node.value, ast.Tuple)
            and len(node.targets) == 1
            and isinstance(node.targets[0], ast.Tuple)
        ):
            for elt in node.value.elts:
                self._expr(elt, mult)
        else:
            self._expr(node.value, mult)

    def _store_name(self, target: ast.AST, loop_ok: bool) -> None:
        if isinstance(target, ast.Name):
            name = target.id
            if name.startswith("_"):
                self.fail(target, "dunder", f"names starting with '_' are not allowed ({name!r})")
            elif name in RESERVED_NAMES or name == self.factor:
                self.fail(target, "mutation", f"cannot assign to the reserved name {name!r}")
            elif name in self.loop_vars and not loop_ok:
                self.fail(target, "loop-var", f"the loop variable {name!r} may not be assigned")
        elif isinstance(target, ast.Attribute):
            self.fail(target, "mutation", "assigning to an attribute is not allowed (factors keep no state)")
        elif isinstance(target, ast.Subscript):
            self.fail(target, "mutation", "assigning to an item is not allowed (arrays are read-only)")
        elif isinstance(target, ast.Starred):
            self.fail(target, "construct", "starred assignment is not allowed")
        else:
            self.fail(target, "construct", f"cannot assign to {type(target).__name__}")

    def _for(self, node: ast.For, mult: int) -> None:
        if node.orelse:
            self.fail(node, "loop", "for ... else is not allowed")
        if not isinstance(node.target, ast.Name):
            self.fail(node, "loop", "the loop target must be a single name")
        else:
            self._store_name(node.target, loop_ok=True)
            if node.target.id in self.locals_:
                self.fail(node.target, "loop-var", f"{node.target.id!r} is both a loop variable and a local")
        count = self._range_count(node.iter)
        inner = mult
        if count is None:
            self.fail(node, "loop", "loops must iterate over range(CONST) with integer literal bounds")
        elif count > MAX_LOOP_ITERATIONS:
            self.fail(
                node, "loop", f"range has {count} iterations; at most {MAX_LOOP_ITERATIONS} are allowed"
            )
        elif mult * count > MAX_TOTAL_ITERATIONS:
            self.fail(
                node,
                "loop",
                f"nested loops run {mult * count} iterations; at most {MAX_TOTAL_ITERATIONS} are allowed",
            )
        else:
            inner = mult * max(count, 1)
        self._block(node.body, inner, in_loop=True)

    @staticmethod
    def _range_count(node: ast.AST) -> int | None:
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "range"):
            return None
        if node.keywords or not 1 <= len(node.args) <= 3:
            return None
        values = [int_literal(arg) for arg in node.args]
        if any(v is None or abs(v) > MAX_INT_LITERAL for v in values):
            return None
        ints = [v for v in values if v is not None]
        if len(ints) == 3 and ints[2] == 0:
            return None
        return len(range(*ints))

    # -- expressions
    def _expr(self, node: ast.AST, mult: int) -> None:
        self.cost += mult
        if isinstance(node, ast.Constant):
            self._constant(node, index=False)
        elif isinstance(node, ast.Name):
            self._load_name(node)
        elif isinstance(node, ast.Attribute):
            self._attribute_value(node)
        elif isinstance(node, ast.Subscript):
            self._expr(node.value, mult)
            self._index(node.slice)
        elif isinstance(node, ast.BinOp):
            self._binop_check(node, node.op, node.right)
            self._expr(node.left, mult)
            if not isinstance(node.op, ast.Pow):
                self._expr(node.right, mult)
        elif isinstance(node, ast.UnaryOp):
            if isinstance(node.op, ast.Not):
                self.fail(node, "construct", "'not' is not allowed; use np.logical_not(x) or ~mask")
            self._expr(node.operand, mult)
        elif isinstance(node, ast.BoolOp):
            for value in node.values:
                self._expr(value, mult)
        elif isinstance(node, ast.Compare):
            for op in node.ops:
                if not isinstance(op, _OK_CMPOPS):
                    self.fail(node, "construct", f"comparison {type(op).__name__} is not allowed")
            self._expr(node.left, mult)
            for comp in node.comparators:
                self._expr(comp, mult)
        elif isinstance(node, ast.IfExp):
            self._expr(node.test, mult)
            self._expr(node.body, mult)
            self._expr(node.orelse, mult)
        elif isinstance(node, ast.Call):
            self._call(node, mult)
        elif isinstance(node, ast.JoinedStr | ast.FormattedValue):
            self.fail(node, "string", "f-strings are not allowed")
        elif isinstance(node, ast.Tuple):
            self.fail(node, "construct", "tuples are only allowed in assignments and axis=(...)")
        elif isinstance(node, ast.Lambda):
            self.fail(node, "construct", "lambda is not allowed")
        elif isinstance(node, ast.ListComp | ast.SetComp | ast.DictComp | ast.GeneratorExp):
            self.fail(node, "construct", "comprehensions are not allowed")
        elif isinstance(node, ast.Yield | ast.YieldFrom | ast.Await):
            self.fail(node, "construct", f"{type(node).__name__.lower()} is not allowed")
        elif isinstance(node, ast.Starred):
            self.fail(node, "construct", "starred expressions are not allowed")
        else:
            self.fail(node, "construct", f"{type(node).__name__} expressions are not allowed")

    def _constant(self, node: ast.Constant, index: bool) -> None:
        value = node.value
        if isinstance(value, str | bytes):
            self.fail(node, "string", "string and bytes values are not allowed")
        elif value is Ellipsis:
            if not index:
                self.fail(node, "construct", "'...' is only allowed inside an index")
        elif isinstance(value, bool):
            pass
        elif type(value) is int:
            if abs(value) > MAX_INT_LITERAL:
                self.fail(
                    node,
                    "constant",
                    f"integer literal {value if abs(value) < 10**30 else '(huge)'} exceeds {MAX_INT_LITERAL}",
                )
        elif type(value) is float:
            if not math.isfinite(value):
                self.fail(node, "constant", "non-finite float literal")
        else:
            self.fail(node, "constant", f"{type(value).__name__} literals are not allowed")

    def _load_name(self, node: ast.Name) -> None:
        name = node.id
        if name in _IMPORT_NAMES:
            self.fail(node, "import", f"{name!r} is not available: imports are not allowed")
        elif name.startswith("_"):
            self.fail(node, "dunder", f"names starting with '_' are not allowed ({name!r})")
        elif name == self.factor:
            self.fail(node, "recursion", "a factor may not refer to itself")
        elif name == "a":
            if self.kind in STATE_ONLY_TYPES:
                self.fail(node, "phi-action", f"a {self.kind} factor is state-only and may not read the action a")
        elif name == "s":
            self.fail(node, "attribute", "s may only be read as s.<feature> or s.obs")
        elif name in ("np", "math"):
            self.fail(node, "attribute", f"{name} may only be used as {name}.<allowed name>")
        elif name in BUILTIN_FUNCTIONS or name == "range":
            self.fail(node, "call", f"{name} may only be called")
        elif name in self.loop_vars:
            self.fail(node, "loop-var", f"the loop variable {name!r} may only be used as an array index")
        elif name in self.locals_:
            pass
        elif name in _BUILTIN_NAMES:
            self.fail(node, "builtin", f"the builtin {name!r} is not available to factors")
        else:
            self.fail(node, "name", f"unknown name {name!r}")

    def _attribute_value(self, node: ast.Attribute) -> None:
        """An attribute read as a value (not called)."""
        attr = node.attr
        if attr.startswith("_"):
            self.fail(node, "dunder", f"attributes starting with '_' are not allowed ({attr!r})")
            return
        base = node.value
        if isinstance(base, ast.Name) and base.id == "s":
            if attr != "obs" and self.features is not None and attr not in self.features:
                self.fail(
                    node,
                    "feature",
                    f"the state has no feature {attr!r} (declared: {', '.join(sorted(self.features))}, obs)",
                )
        elif isinstance(base, ast.Name) and base.id == "np":
            if attr in NUMPY_FUNCTIONS or attr == "linalg":
                self.fail(node, "numpy", f"np.{attr} may only be called")
            elif attr not in NUMPY_CONSTANTS:
                self.fail(node, "numpy", f"np.{attr} is not an allowed NumPy name")
        elif is_np_linalg(base):
            if attr in NUMPY_LINALG_FUNCTIONS:
                self.fail(node, "numpy", f"np.linalg.{attr} may only be called")
            else:
                self.fail(node, "numpy", f"np.linalg.{attr} is not an allowed NumPy name")
        elif isinstance(base, ast.Name) and base.id == "math":
            if attr not in MATH_CONSTANTS:
                self.fail(node, "attribute", f"math.{attr} is not allowed (only math.pi, math.e, math.tau)")
        else:
            self._attribute_base_problem(node)

    def _attribute_base_problem(self, node: ast.Attribute) -> None:
        """Attribute on anything other than s/np/math: report the most telling problem once."""
        for sub in ast.walk(node):
            if isinstance(sub, ast.Attribute) and sub.attr.startswith("_"):
                self.fail(node, "dunder", f"attributes starting with '_' are not allowed ({sub.attr!r})")
                return
        if isinstance(node.value, ast.Name) and node.value.id == "a" and self.kind in STATE_ONLY_TYPES:
            self.fail(node, "phi-action", f"a {self.kind} factor is state-only and may not read the action a")
            return
        root: ast.AST = node
        while isinstance(root, ast.Attribute):
            root = root.value
        if isinstance(root, ast.Name) and root.id == "np":
            self.fail(node, "numpy", f"{ast.unparse(node)} is not an allowed NumPy name")
            return
        if isinstance(root, ast.Name) and root.id in _IMPORT_NAMES:
            self.fail(node, "import", f"{root.id!r} is not available: imports are not allowed")
            return
        self.fail(
            node,
            "attribute",
            f"attribute .{node.attr} is not allowed here (only s.<feature>, s.obs, np.<function>)",
        )

    def _index(self, node: ast.AST) -> None:
        elts = node.elts if isinstance(node, ast.Tuple) else [node]
        for elt in elts:
            if isinstance(elt, ast.Slice):
                if elt.lower is not None or elt.upper is not None or elt.step is not None:
                    self.fail(
                        elt, "subscript", "slices with bounds are not allowed; use ':' or an integer index"
                    )
            elif (isinstance(elt, ast.Constant) and elt.value is Ellipsis) or (
                isinstance(elt, ast.Name) and elt.id in self.loop_vars
            ):
                pass
            elif (value := int_literal(elt)) is not None:
                if abs(value) > MAX_INT_LITERAL:
                    self.fail(elt, "constant", "index literal out of range")
            else:
                self.fail(
                    elt, "subscript", "an index must be an integer literal, a loop variable, ':' or '...'"
                )

    def _binop_check(self, node: ast.AST, op: ast.operator, right: ast.AST) -> None:
        if not isinstance(op, _OK_BINOPS):
            self.fail(node, "construct", f"operator {type(op).__name__} is not allowed")
        if isinstance(op, ast.Pow):
            self._power_exponent(right)

    def _power_exponent(self, node: ast.AST) -> None:
        value = numeric_literal(node)
        if value is None:
            self.fail(
                node,
                "power",
                "the exponent must be a numeric literal (use np.exp/np.exp2 for powers of variables)",
            )
        elif abs(value) > MAX_POWER:
            self.fail(node, "power", f"exponent {value} exceeds {MAX_POWER} in magnitude")

    def _call(self, node: ast.Call, mult: int) -> None:
        func = node.func
        spec: ArgSpec | None = None
        label = ""
        if isinstance(func, ast.Name):
            name = func.id
            if name in BUILTIN_FUNCTIONS:
                lo, hi = BUILTIN_FUNCTIONS[name]
                spec, label = ArgSpec(lo, hi), name
            elif name == "range":
                self.fail(node, "loop", "range() may only appear as the iterable of a for loop")
                return
            else:
                self._load_name(func)
                if name in self.locals_ and not name.startswith("_") and name not in self.loop_vars:
                    self.fail(node, "call", f"{name!r} is a value, not a function")
                self._walk_args(node, mult)
                return
        elif isinstance(func, ast.Attribute):
            if func.attr.startswith("_"):
                self.fail(func, "dunder", f"attributes starting with '_' are not allowed ({func.attr!r})")
                return
            if isinstance(func.value, ast.Name) and func.value.id == "np":
                spec, label = NUMPY_FUNCTIONS.get(func.attr), f"np.{func.attr}"
                if spec is None:
                    self.fail(func, "numpy", f"{label} is not an allowed NumPy function")
                    return
            elif is_np_linalg(func.value):
                spec, label = NUMPY_LINALG_FUNCTIONS.get(func.attr), f"np.linalg.{func.attr}"
                if spec is None:
                    self.fail(func, "numpy", f"{label} is not an allowed NumPy function")
                    return
            else:
                before = len(self.violations)
                self._attribute_value(func)
                if len(self.violations) == before:
                    self.fail(node, "call", "only np.<function> and abs/min/max/float may be called")
                self._walk_args(node, mult)
                return
        else:
            self.fail(node, "call", "only np.<function> and abs/min/max/float may be called")
            self._expr(func, mult)
            self._walk_args(node, mult)
            return
        self._check_call_args(node, spec, label, mult)

    def _walk_args(self, node: ast.Call, mult: int) -> None:
        for arg in node.args:
            self._expr(arg, mult)
        for kw in node.keywords:
            self._expr(kw.value, mult)

    def _check_call_args(self, node: ast.Call, spec: ArgSpec, label: str, mult: int) -> None:
        n = len(node.args)
        if not spec.min_pos <= n <= spec.max_pos:
            want = str(spec.min_pos) if spec.min_pos == spec.max_pos else f"{spec.min_pos} to {spec.max_pos}"
            self.fail(node, "call", f"{label} takes {want} positional argument(s), got {n}")
        for i, arg in enumerate(node.args):
            if isinstance(arg, ast.Starred):
                self.fail(arg, "construct", "starred arguments are not allowed")
            elif i in spec.int_positions:
                if int_literal(arg) is None:
                    self.fail(arg, "call", f"argument {i + 1} of {label} must be an integer literal")
            elif i in spec.power_positions:
                self._power_exponent(arg)
            else:
                self._expr(arg, mult)
        for kw in node.keywords:
            if kw.arg is None:
                self.fail(kw.value, "construct", "**kwargs is not allowed")
                continue
            kind = spec.keywords.get(kw.arg)
            if kind is None:
                self.fail(kw.value, "call", f"{label} does not accept the keyword {kw.arg!r} here")
            elif kind == "axis":
                items = kw.value.elts if isinstance(kw.value, ast.Tuple) else [kw.value]
                if not items or any(int_literal(item) is None for item in items):
                    self.fail(kw.value, "call", "axis must be an integer literal or a tuple of them")
            elif int_literal(kw.value) is None:
                self.fail(kw.value, "call", f"{kw.arg} must be an integer literal")




# --------------------------------------------------------------------------- public API


def check_code(name: str, kind: str, code: Any, features: Iterable[str] | None = None) -> list[Violation]:
    """Every static violation of one factor's code; empty when the code is admissible.

    ``features`` are the task card's feature names; with None, ``s.<name>`` reads are not checked
    against a card (everything else is).
    """
    if not isinstance(code, str):
        return [Violation(name, "syntax", 0, "code must be a string")]
    if len(code) > MAX_CODE_CHARS:
        return [
            Violation(name, "size", 0, f"code is {len(code)} characters; at most {MAX_CODE_CHARS} allowed")
        ]
    try:
        tree = ast.parse(code, mode="exec")
    except SyntaxError as exc:
        return [Violation(name, "syntax", int(exc.lineno or 0), f"does not parse: {exc.msg}")]
    except (ValueError, RecursionError, MemoryError) as exc:
        return [
            Violation(
                name,
                "size" if not isinstance(exc, ValueError) else "syntax",
                0,
                f"does not parse: {type(exc).__name__}",
            )
        ]
    problem = _size_problem(tree)
    if problem is not None:
        return [Violation(name, "size", 0, problem)]
    checker = _FunctionChecker(name, kind, frozenset(features) if features is not None else None)
    functions = [stmt for stmt in tree.body if isinstance(stmt, ast.FunctionDef)]
    target = next((fn for fn in functions if fn.name == name), functions[0] if functions else None)
    for stmt in tree.body:
        if stmt is target:
            continue
        if isinstance(stmt, ast.Import | ast.ImportFrom):
            checker.fail(stmt, "import", "imports are not allowed")
        elif isinstance(stmt, ast.FunctionDef):
            checker.fail(stmt, "module", f"a second function {stmt.name!r}: only one def is allowed")
        else:
            checker.fail(stmt, "module", f"{type(stmt).__name__} at module level: only one def is allowed")
    if target is None:
        checker.fail(
            tree.body[0] if tree.body else None,
            "module",
            f"no function definition: write def {name}({', '.join(_PARAMS.get(kind, ['s']))}): ...",
        )
    else:
        try:
            checker.check_function(target)
        except RecursionError:
            checker.fail(target, "size", "the code is nested too deeply to check")
    return checker.violations


def check_metadata(factor: Factor) -> list[Violation]:
    """Documented semantics: doc, units and range_hint present; the range readable as [lo, hi]."""
    out: list[Violation] = []
    for key in ("doc", "units", "range_hint"):
        value = getattr(factor, key)
        if not isinstance(value, str) or not value.strip():
            out.append(Violation(factor.name, "metadata", 0, f"{key} is missing or empty"))
    if (
        isinstance(factor.range_hint, str)
        and factor.range_hint.strip()
        and parse_range_hint(factor.range_hint) is None
    ):
        out.append(
            Violation(
                factor.name,
                "range-hint",
                0,
                f"range_hint {factor.range_hint!r} does not read as '[lo, hi]'",
                "warning",
            )
        )
    return out


def check_factor(factor: Factor, features: Iterable[str] | None = None) -> list[Violation]:
    """Code and metadata violations of one factor."""
    return check_code(factor.name, factor.type, factor.code, features) + check_metadata(factor)


def feature_names_of(card_or_features: TaskCard | Iterable[str] | None) -> list[str] | None:
    """The feature names of a task card, or the given names themselves (None stays None)."""
    if card_or_features is None:
        return None
    names = getattr(card_or_features, "feature_names", None)
    if names is not None:
        return [str(n) for n in names]
    return [str(n) for n in card_or_features]  # type: ignore[union-attr]


def check_program(
    program: FactorProgram, card_or_features: TaskCard | Iterable[str] | None = None
) -> StaticReport:
    """All static violations of a program against a task card (or a list of feature names)."""
    features = feature_names_of(card_or_features)
    found: list[Violation] = []
    if not program.phi_factors:
        found.append(
            Violation("<program>", "program", 0, "a program needs at least one PHI factor to feed Φ(s)")
        )
    if len(program.factors) > MAX_FACTORS:
        found.append(
            Violation("<program>", "size", 0, f"{len(program.factors)} factors; at most {MAX_FACTORS}")
        )
    for factor in program.factors:
        found.extend(check_factor(factor, features))
    return StaticReport(tuple(found))
