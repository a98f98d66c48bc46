"""The factor language's vocabulary: which NumPy functions, constants and builtins factor code may use.

This one table drives both the static checker (what may be *written*) and the restricted namespace
the compiled code runs in (what *exists* at run time), so the two cannot drift apart: a name the
checker accepts is the only kind of name the namespace provides.

Every function here is pure, element-wise or a reduction, allocates at most as much as its inputs,
and runs in time linear in its inputs. Anything that creates arrays of an arbitrary shape
(``np.ones``, ``np.empty``, ``np.arange``), reads or writes files (``np.load``, ``np.save``,
``np.fromfile``, ``np.memmap``), reaches Python objects (``np.frompyfunc``, ``np.vectorize``,
``np.lib``, ``np.ctypeslib``), is random, or runs a super-linear algorithm is left out on purpose.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class ArgSpec:
    """How a whitelisted function may be called.

    ``int_positions`` are positional slots that must be literal integers (e.g. ``decimals`` of
    ``np.round``, an axis given positionally); ``power_positions`` must be numeric constants of
    bounded magnitude (the exponent of ``np.power``); ``keywords`` maps each allowed keyword to the
    kind of literal it takes (``"axis"``: an int or a tuple of ints; ``"int"``: an int).
    """

    min_pos: int
    max_pos: int
    int_positions: frozenset[int] = frozenset()
    power_positions: frozenset[int] = frozenset()
    keywords: Mapping[str, str] = field(default_factory=dict)


_UNARY = ArgSpec(1, 1)
_BINARY = ArgSpec(2, 2)
_REDUCE = ArgSpec(1, 2, int_positions=frozenset({1}), keywords={"axis": "axis"})

#: name -> call spec of every ``np.<name>`` function a factor may call.
NUMPY_FUNCTIONS: dict[str, ArgSpec] = {
    **{
        name: _UNARY
        for name in (
            "abs",
            "absolute",
            "fabs",
            "sqrt",
            "cbrt",
            "square",
            "exp",
            "exp2",
            "expm1",
            "log",
            "log2",
            "log10",
            "log1p",
            "tanh",
            "sinh",
            "cosh",
            "arcsinh",
            "arccosh",
            "arctanh",
            "sin",
            "cos",
            "tan",
            "arctan",
            "arcsin",
            "arccos",
            "sign",
            "floor",
            "ceil",
            "rint",
            "trunc",
            "deg2rad",
            "rad2deg",
            "isfinite",
            "logical_not",
            "ones_like",
            "zeros_like",
        )
    },
    **{
        name: _BINARY
        for name in (
            "arctan2",
            "hypot",
            "minimum",
            "maximum",
            "fmin",
            "fmax",
            "heaviside",
            "logaddexp",
            "copysign",
            "logical_and",
            "logical_or",
            "logical_xor",
            "full_like",
        )
    },
    "power": ArgSpec(2, 2, power_positions=frozenset({1})),
    "clip": ArgSpec(3, 3),
    "where": ArgSpec(3, 3),
    **{name: _REDUCE for name in ("sum", "mean", "max", "min", "amax", "amin", "prod", "std", "var")},
    "round": ArgSpec(1, 2, int_positions=frozenset({1}), keywords={"decimals": "int"}),
    "around": ArgSpec(1, 2, int_positions=frozenset({1}), keywords={"decimals": "int"}),
}

#: ``np.linalg.<name>``: only the vector/Frobenius norm (no ``ord``: matrix norms run an SVD).
NUMPY_LINALG_FUNCTIONS: dict[str, ArgSpec] = {"norm": ArgSpec(1, 1, keywords={"axis": "axis"})}

#: ``np.<name>`` constants (``np.inf`` and ``np.nan`` are left out: a factor must stay finite).
NUMPY_CONSTANTS: dict[str, float] = {"pi": math.pi, "e": math.e}

#: ``math.<name>`` constants; no ``math`` functions (np covers them, vectorised).
MATH_CONSTANTS: dict[str, float] = {"pi": math.pi, "e": math.e, "tau": math.tau}

#: Builtins a factor may call, with their arity (min, max); no keywords.
BUILTIN_FUNCTIONS: dict[str, tuple[int, int]] = {"abs": (1, 1), "min": (2, 8), "max": (2, 8), "float": (1, 1)}

#: Names a factor may not assign to (they would shadow the vocabulary or the arguments).
RESERVED_NAMES: frozenset[str] = frozenset(
    {"s", "a", "np", "math", "range", "True", "False", "None", *BUILTIN_FUNCTIONS}
)

#: Magnitude bounds on literals: integers beyond this are refused, exponents of ** beyond this too.
MAX_INT_LITERAL = 10**9
MAX_POWER = 16


class ReadOnlyNamespace:
    """An attribute bag that cannot be changed after construction.

    It stands in for ``np``/``math`` inside factor code. The checker already forbids attribute
    assignment; refusing it here as well means a bug in the checker still cannot let one factor
    change the functions another factor sees.
    """

    def __init__(self, label: str, members: Mapping[str, Any]) -> None:
        object.__setattr__(self, "_label", label)
        self.__dict__.update(members)

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"{object.__getattribute__(self, '_label')} is read-only")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"{object.__getattribute__(self, '_label')} is read-only")

    def __repr__(self) -> str:
        return f"<restricted {object.__getattribute__(self, '_label')}>"


def _numpy_proxy() -> ReadOnlyNamespace:
    members: dict[str, Any] = {name: getattr(np, name) for name in NUMPY_FUNCTIONS}
    members.update({name: np.float64(value) for name, value in NUMPY_CONSTANTS.items()})
    members["linalg"] = ReadOnlyNamespace(
        "np.linalg", {name: getattr(np.linalg, name) for name in NUMPY_LINALG_FUNCTIONS}
    )
    return ReadOnlyNamespace("np", members)


def _math_proxy() -> ReadOnlyNamespace:
    return ReadOnlyNamespace("math", {name: np.float64(value) for name, value in MATH_CONSTANTS.items()})


NP_PROXY = _numpy_proxy()
MATH_PROXY = _math_proxy()

_BUILTIN_OBJECTS: dict[str, Callable[..., Any]] = {
    "abs": abs,
    "min": min,
    "max": max,
    # float() returns a NumPy float64 so that no Python-level number ever leaves a factor's
    # arithmetic (see compiler.py: Python ints are unbounded, NumPy scalars are not).
    "float": np.float64,
}


def base_globals() -> dict[str, Any]:
    """A fresh globals dict for one factor: no builtins beyond the whitelist."""
    env: dict[str, Any] = {"__builtins__": {}, "np": NP_PROXY, "math": MATH_PROXY, "range": range}
    env.update(_BUILTIN_OBJECTS)
    return env


def allowed_syntax_summary() -> str:
    """The factor language in a few lines, for prompts and error messages."""
    funcs = ", ".join(sorted(NUMPY_FUNCTIONS))
    return (
        "Write exactly one function: def NAME(s) for a PHI (state-only) factor or def NAME(s, a) for an "
        "AUX (state-action) factor; NAME equals the factor's name. No imports, no other statements.\n"
        "Inside: arithmetic (+ - * / // % ** with a constant exponent |p| <= 16), comparisons, & | ~, "
        "and/or, x if c else y, local assignment (also +=, tuple unpacking), if/elif/else, "
        "for i in range(CONST) with i used only as an array index, return.\n"
        "Read the state only as s.<feature> (float arrays of shape [B]) or s.obs ([B, obs_dim]); "
        "a is [B, act_dim]. Index with integer constants, ':' or '...', e.g. s.obs[:, 3], a[:, i].\n"
        f"Call only np.{{{funcs}}}, np.linalg.norm(x, axis=...), abs, min, max, float. "
        "Reductions take axis=...; no keepdims/out/dtype. Constants: np.pi, np.e, math.pi, math.e, "
        "math.tau. No strings, lists, lambdas, comprehensions, while, try, with, global, attributes "
        "other than these, or names starting with '_'.\n"
        "Return a float array of shape [B] (one value per state), finite and bounded."
    )
