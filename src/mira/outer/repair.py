"""The structural-flaw trigger of the outer loop: when the returns show that the program misses what the
task pays for.

MCM (section 4.3) watches learning dynamics for anomalies relative to the run's own healthy history. A
program that is wrong from the first step has no healthy history to depart from, so MIRA also asks the
return decomposition directly, every cycle: does a task feature explain episodic returns the program's
factors cannot (:mod:`mira.shaping.attribution`), and most of what they leave unexplained?
``repair_cycles`` cycles in a row of such a gain call SRR with the attribution as evidence; after an
intervention the check rests ``repair_cooldown`` cycles.
"""

from __future__ import annotations

from typing import Any

from mira.outer.config import OuterLoopConfig
from mira.shaping.attribution import ReturnAttribution, attribute_returns, cv_r2
from mira.shaping.factors import FactorSource
from mira.shaping.source import HarsReward
from mira.tasks.card import TaskCard


class StructuralCheck:
    """Measures the attribution each cycle and says when it warrants a repair."""

    def __init__(self, config: OuterLoopConfig, card: TaskCard, hars: HarsReward) -> None:
        self.config, self.card, self.hars = config, card, hars
        self.streak = 0
        self.cooldown = 0
        self.latest: ReturnAttribution | None = None

    def _episodes(self) -> tuple[list[Any], Any] | None:
        rows, returns = self.hars.memory.recent_episodes(self.config.repair_max_episodes)
        if len(rows) < self.config.repair_min_episodes:
            return None
        return rows, returns

    def observe(self) -> ReturnAttribution | None:
        """This cycle's attribution (None before enough episodes are stored); updates the streak."""
        cfg = self.config
        found = self._episodes()
        self.cooldown = max(0, self.cooldown - 1)
        if found is None:
            self.latest = None
            self.streak = 0
            return None
        rows, returns = found
        memory = self.hars.memory
        sums, ranges = memory.feature_sums(rows, self.card.feature_values)
        hc = self.hars.config
        self.latest = attribute_returns(memory.head_sums(rows), returns, sums, hc.decompose_ridge,
                                        cfg.repair_folds, ranges,
                                        centred=hc.decompose_ridge_centred, select=hc.decompose_ridge_select)
        best = self.latest.best
        counts = best is not None and best.gain >= cfg.repair_min_gain and best.share >= cfg.repair_min_share
        self.streak = self.streak + 1 if counts else 0
        return self.latest

    @property
    def triggered(self) -> bool:
        return self.streak >= self.config.repair_cycles and self.cooldown == 0

    def rest(self) -> None:
        """An intervention happened (for whatever reason): let the next program be measured afresh."""
        self.streak = 0
        self.cooldown = self.config.repair_cooldown

    def explain(self, factors: FactorSource) -> float:
        """Out-of-sample R² of the stored returns decomposed over ``factors`` (SRR's return-explanation
        check; the same episodes and folds as the attribution)."""
        found = self._episodes()
        if found is None:
            return float("nan")
        rows, returns = found
        hc = self.hars.config
        return cv_r2(self.hars.memory.head_sums(rows, factors), returns, hc.decompose_ridge,
                     self.config.repair_folds,
                     centred=hc.decompose_ridge_centred, select=hc.decompose_ridge_select)

    def state_dict(self) -> dict[str, Any]:
        return {"streak": self.streak, "cooldown": self.cooldown}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.streak, self.cooldown = int(state.get("streak", 0)), int(state.get("cooldown", 0))
