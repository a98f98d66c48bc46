"""What a rejected factor is told: one :class:`Violation` per broken rule, with a stable rule id.

Rule ids are part of the interface: tests, run logs and the SRR prompt refer to them, so a caller
can tell *why* a candidate was refused (an import is not a NaN). ``RULES`` documents every id.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Severity = Literal["error", "warning"]

#: Every rule id a check may report, with what it means.
RULES: dict[str, str] = {
    # structure
    "syntax": "the code does not parse as Python",
    "size": "the code is too long, too deeply nested or too costly (static operation bound)",
    "module": "the module must contain exactly one function definition and nothing else",
    "signature": "the function must be def NAME(s) for PHI or def NAME(s, a) for AUX",
    "decorator": "decorators are not allowed",
    "default": "default argument values are not allowed (they keep state between calls)",
    "annotation": "annotations must be plain names (they are dropped before compilation)",
    "return": "the function must return a value (bare return is not allowed)",
    # forbidden constructs
    "construct": "a Python construct outside the factor language (lambda, comprehension, try, ...)",
    "import": "imports in any spelling are not allowed",
    "global": "global/nonlocal declarations are not allowed",
    "dunder": "names or attributes starting with an underscore are not allowed",
    "builtin": "this Python builtin is not available to factors",
    "name": "an unknown name (neither an argument, a local, np, math, abs, min, max nor float)",
    "recursion": "a factor may not refer to itself",
    "string": "string and bytes values are not allowed",
    "constant": "a numeric constant is out of range (huge integer, non-finite float) or not numeric",
    "power": "the exponent of ** or np.power must be a numeric constant of magnitude <= 16",
    "loop": "only for NAME in range(CONST) with a small constant bound is allowed",
    "loop-var": "a loop variable may only be used as an array index",
    "subscript": "indices must be integer constants, loop variables, ':' or '...'",
    "mutation": "assignment is only to local names (no attributes, items, arguments or reserved names)",
    "attribute": "attribute access is only s.<feature>, s.obs and np.<allowed>",
    "numpy": "this NumPy name is not in the whitelist of pure element-wise/reduction functions",
    "call": "only whitelisted functions may be called, with the allowed arguments",
    "feature": "the state has no such feature (reading undeclared or future quantities is not allowed)",
    "phi-action": "a PHI (state-only) factor may not read the action",
    "unguarded": "a division, logarithm or square root of a state- or action-dependent value that the code does "
                 "not provably keep in the operation's domain (away from 0, above 0, at or above 0) wherever the "
                 "task goes: guard it, e.g. np.maximum(x, c), abs(x) + c or c + x ** 2 with c > 0",
    # metadata
    "metadata": "doc, units and range_hint must be given",
    "range-hint": "range_hint should read '[lo, hi]' with lo <= hi",
    "program": "a program-level problem (schema, duplicate names, task mismatch)",
    # sandbox realizability (section 4.4.4)
    "sandbox-timeout": "the factor did not finish within its time limit",
    "sandbox-memory": "the factor exceeded its memory limit",
    "sandbox-crash": "the worker process died while running the factor",
    "sandbox-error": "the factor raised an exception on real states",
    "shape": "the factor must return a float array of shape [B]",
    "non-finite": "the factor returned NaN or Inf on real states",
    "kurtosis": "the factor's outputs are too heavy-tailed (excess kurtosis above the bound)",
    "saturation": "too many outputs sit at the extremes (saturation ratio above the bound)",
    "lipschitz": "the factor is too steep (quantile of finite-difference gradient norms above the bound)",
    "batch-coupling": "a state's value depends on the other states in the batch",
    "singular": "a division, logarithm or square root whose argument reaches 0 (or below) on the sandbox's "
                "states or over the range the task card declares for the feature it reads",
}


@dataclass(frozen=True)
class Violation:
    """One broken rule: which factor, which rule, where (1-based line; 0 = not tied to a line)."""

    factor: str
    rule: str
    line: int
    message: str
    severity: Severity = "error"

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise ValueError(f"unknown rule id {self.rule!r}")

    @property
    def is_error(self) -> bool:
        return self.severity == "error"

    def __str__(self) -> str:
        tag = "" if self.is_error else "warning: "
        return f"{tag}{self.factor}:{self.line}: [{self.rule}] {self.message}"

    def to_dict(self) -> dict[str, object]:
        return {
            "factor": self.factor,
            "rule": self.rule,
            "line": self.line,
            "message": self.message,
            "severity": self.severity,
        }
