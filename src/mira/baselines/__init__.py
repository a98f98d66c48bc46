"""The paper's comparison baselines (section 5.1.2) as reward sources of the one trainer.

* :class:`~mira.baselines.ircr.IRCRReward`  — IRCR: normalised trajectory return as uniform credit.
* :class:`~mira.baselines.rd.RDReward`      — RD: linear reward, ridge least squares on trajectories.
* :class:`~mira.baselines.lare.LaReReward`  — LaRe: static LLM factor program + return-decomposition decoder.
* :class:`~mira.baselines.vib.VIBReward`    — VIB: information-bottleneck reward model + return decomposition.

All of them sample only finished episodes, read episodes from the replay buffer by row ranges
(:mod:`.episodes`), never read the dense reward for their reward (only :mod:`.diagnostics` does, for
the logged ``corr_dense``), and are configured by :class:`~mira.baselines.config.BaselinesConfig`
(``TrainConfig.baselines``). Each module's docstring says where ours differs from its paper.

Attributes are imported lazily so that ``mira.config`` (which imports :mod:`.config`) stays light.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

from mira.baselines.config import BaselinesConfig, DecoderConfig, IRCRConfig, LaReConfig, RDConfig, VIBConfig

_LAZY = {
    "IRCRReward": "mira.baselines.ircr",
    "RDReward": "mira.baselines.rd",
    "LaReReward": "mira.baselines.lare",
    "ProgramFactors": "mira.baselines.lare",
    "VIBReward": "mira.baselines.vib",
    "EpisodeStore": "mira.rewards.episodes",
    "build_baseline": "mira.baselines.factory",
    "BASELINES": "mira.baselines.factory",
}

__all__ = [
    "BASELINES",
    "BaselinesConfig",
    "DecoderConfig",
    "EpisodeStore",
    "IRCRConfig",
    "IRCRReward",
    "LaReConfig",
    "LaReReward",
    "ProgramFactors",
    "RDConfig",
    "RDReward",
    "VIBConfig",
    "VIBReward",
    "build_baseline",
]


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mira.baselines' has no attribute {name!r}")
    return getattr(import_module(module), name)
