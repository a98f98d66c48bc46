"""What a factor's code is, before any rule about what it may do: its two kinds and its parse.

Both the program model (which refuses a PHI factor that reads the action) and the static checker
read these; neither depends on the other for them.
"""

from __future__ import annotations

import ast

FACTOR_TYPES = ("PHI", "AUX", "SHAPE")
"""PHI: state-only ``(s)``, feeds the decomposition head and Φ; AUX: state–action ``(s, a)``, feeds the
head, never Φ; SHAPE: state-only ``(s)``, a shaping potential Ψ(s) that enters the agent's reward only as
γΨ(s′) − Ψ(s), never fitted to the returns (:mod:`mira.shaping.source`)."""

STATE_ONLY_TYPES = ("PHI", "SHAPE")
"""The types whose code takes ``(s)`` alone and may not read the action."""

MAX_CODE_CHARS = 8000
"""Longest factor code accepted, checked before parsing so the parser's work is bounded."""


def parse_factor_code(code: str) -> ast.Module:
    """Parse factor code, bounding the work first.

    Raises SyntaxError, ValueError (too long, NUL bytes), RecursionError or MemoryError.
    """
    if len(code) > MAX_CODE_CHARS:
        raise ValueError(f"code is {len(code)} characters long; at most {MAX_CODE_CHARS} are allowed")
    return ast.parse(code, mode="exec")


def reads_action(code: str) -> bool:
    """Whether code has an ``a`` parameter or mentions the name ``a`` (False when it does not parse)."""
    try:
        tree = parse_factor_code(code)
    except (SyntaxError, ValueError, RecursionError, MemoryError):
        return False
    for node in ast.walk(tree):
        if isinstance(node, ast.Name) and node.id == "a":
            return True
        if isinstance(node, ast.arg) and node.arg == "a":
            return True
    return False
