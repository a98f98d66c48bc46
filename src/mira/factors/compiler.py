"""Turn admissible factor code into a Python function that runs in a namespace with nothing in it.

Used both by the sandbox worker and by the in-process evaluator, so the sandbox tests exactly the
function that training will call.

Compilation does three things to the checked AST before ``compile``:

1. drops the docstring and annotations (inert, but an annotation would be *evaluated* at ``def``
   time, which is code running outside the factor call);
2. replaces every numeric literal in a value position by a read-only global holding a NumPy
   ``float64`` (booleans become ``np.bool_``). Python integers are unbounded: ``x = x * x`` repeated
   on a Python int grows without limit, and even ``(c > 0) + (c > 0)`` makes one from two bools.
   With every literal a NumPy scalar, ``float()`` mapped to ``np.float64`` and the checker confining
   loop variables and raw integer literals to index/axis/``range``/exponent positions, every value a
   factor computes is a fixed-width NumPy scalar or array: overflow gives ``inf`` (which the
   evaluator counts and zeroes), never a multi-gigabyte integer;
3. executes the single ``def`` in ``whitelist.base_globals()``: ``__builtins__`` is an empty dict, and
   the only names present are the read-only ``np``/``math`` proxies, ``abs``, ``min``, ``max``,
   ``float`` and ``range``. Executing the ``def`` runs no user code (no decorators, defaults or
   annotations survive step 1 and the checker).
"""

from __future__ import annotations

import ast
from collections.abc import Callable
from typing import Any

import numpy as np

from mira.errors import UsageError
from mira.factors.checker import check_code
from mira.factors.violations import Violation
from mira.factors.whitelist import NUMPY_FUNCTIONS, NUMPY_LINALG_FUNCTIONS, ArgSpec, base_globals

FactorFunction = Callable[..., Any]


class InadmissibleCodeError(UsageError):
    """Code that failed the static checker was offered for compilation."""

    def __init__(self, violations: list[Violation]) -> None:
        self.violations = violations
        super().__init__("; ".join(str(v) for v in violations) or "inadmissible factor code")


class _Lowering(ast.NodeTransformer):
    """Steps 1 and 2 of the module docstring."""

    def __init__(self) -> None:
        self.constants: dict[str, Any] = {}
        self._by_value: dict[tuple[type, object], str] = {}

    def _literal_name(self, node: ast.Constant) -> ast.AST:
        value = node.value
        if type(value) is bool:
            boxed: Any = np.bool_(value)
        elif isinstance(value, int | float):
            boxed = np.float64(value)
        else:
            return node
        key = (type(value), value)
        name = self._by_value.get(key)
        if name is None:
            name = f"_k{len(self._by_value)}"
            self._by_value[key] = name
            self.constants[name] = boxed
        return ast.copy_location(ast.Name(id=name, ctx=ast.Load()), node)

    def visit_Constant(self, node: ast.Constant) -> ast.AST:
        return self._literal_name(node)

    def visit_FunctionDef(self, node: ast.FunctionDef) -> ast.AST:
        body = list(node.body)
        if (
            body
            and isinstance(body[0], ast.Expr)
            and isinstance(body[0].value, ast.Constant)
            and isinstance(body[0].value.value, str)
        ):
            body = body[1:] or [ast.Pass()]
        node.body = body
        node.returns = None
        for arg in [*node.args.posonlyargs, *node.args.args, *node.args.kwonlyargs]:
            arg.annotation = None
        node.decorator_list = [self.visit(d) for d in node.decorator_list]
        node.args.defaults = [self.visit(d) for d in node.args.defaults]
        node.body = [self.visit(stmt) for stmt in node.body]
        return node

    def visit_Subscript(self, node: ast.Subscript) -> ast.AST:
        node.value = self.visit(node.value)  # the index keeps its integer literals
        return node

    def visit_BinOp(self, node: ast.BinOp) -> ast.AST:
        node.left = self.visit(node.left)
        if not isinstance(node.op, ast.Pow):  # small literal exponents stay exact
            node.right = self.visit(node.right)
        return node

    def visit_AugAssign(self, node: ast.AugAssign) -> ast.AST:
        if not isinstance(node.op, ast.Pow):
            node.value = self.visit(node.value)
        return node

    def visit_Call(self, node: ast.Call) -> ast.AST:
        spec = _call_spec(node.func)
        if isinstance(node.func, ast.Name) and node.func.id == "range":
            return node
        node.func = self.visit(node.func)
        keep = spec.int_positions | spec.power_positions if spec is not None else frozenset()
        node.args = [arg if i in keep else self.visit(arg) for i, arg in enumerate(node.args)]
        if spec is None:
            for kw in node.keywords:
                kw.value = self.visit(kw.value)
        return node  # whitelisted keywords (axis, decimals) take integer literals and stay as they are


def _call_spec(func: ast.AST) -> ArgSpec | None:
    if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name) and func.value.id == "np":
        return NUMPY_FUNCTIONS.get(func.attr)
    if (
        isinstance(func, ast.Attribute)
        and isinstance(func.value, ast.Attribute)
        and func.value.attr == "linalg"
        and isinstance(func.value.value, ast.Name)
        and func.value.value.id == "np"
    ):
        return NUMPY_LINALG_FUNCTIONS.get(func.attr)
    return None


def compile_factor(
    name: str, kind: str, code: str, features: list[str] | None = None, *, _unchecked: bool = False
) -> FactorFunction:
    """The callable of one factor, after the static checker has admitted its code.

    Raises :class:`InadmissibleCodeError` when the checker finds an error. ``_unchecked`` exists
    only so the test suite can push hostile code into the *sandbox worker* to prove its OS-level
    limits hold on their own; nothing else may pass it.
    """
    if not _unchecked:
        errors = [v for v in check_code(name, kind, code, features) if v.is_error]
        if errors:
            raise InadmissibleCodeError(errors)
    tree = ast.parse(code, mode="exec")
    lowering = _Lowering()
    tree = lowering.visit(tree)
    ast.fix_missing_locations(tree)
    code_obj = compile(tree, f"<factor {name}>", "exec", dont_inherit=True)
    env = base_globals()
    env.update(lowering.constants)
    exec(code_obj, env)  # defines the function; checked code runs nothing at definition time
    fn = env.get(name)
    if not callable(fn):
        raise InadmissibleCodeError([Violation(name, "module", 0, f"no function named {name!r}")])
    return fn
