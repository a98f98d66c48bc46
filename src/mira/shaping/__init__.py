"""HARS: learned potential-based reward shaping over typed reward factors (section 4.2.2).

Only :class:`HarsConfig` is imported eagerly (``mira.config`` embeds it); the networks and the reward
source load on first use so that ``import mira.config`` stays light and free of import cycles.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from mira.shaping.config import HarsConfig

if TYPE_CHECKING:
    from mira.shaping.factors import FactorMeta, FactorSource, FunctionFactorSource, ProgramFactorSource
    from mira.shaping.method import build_hars
    from mira.shaping.source import HarsReward

_LAZY = {
    "HarsReward": "mira.shaping.source",
    "FactorMeta": "mira.shaping.factors",
    "FactorSource": "mira.shaping.factors",
    "FunctionFactorSource": "mira.shaping.factors",
    "ProgramFactorSource": "mira.shaping.factors",
    "build_hars": "mira.shaping.method",
}

__all__ = ["FactorMeta", "FactorSource", "FunctionFactorSource", "HarsConfig", "HarsReward",
           "ProgramFactorSource", "build_hars"]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mira.shaping' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(module), name)
