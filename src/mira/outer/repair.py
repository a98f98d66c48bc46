"""The structural-flaw trigger of the outer loop: when the returns show that the program misses what the
task pays for.

MCM (section 4.3) watches learning dynamics for anomalies relative to the run's own healthy history. A
program that is wrong from the first step has no healthy history to depart from, so MIRA also asks the
return decomposition directly, every cycle: does a task feature explain episodic returns the program's
factors cannot (:mod:`mira.shaping.attribution`), and most of what they leave unexplained?
``REPAIR_CYCLES`` cycles in a row of such a gain call SRR with the attribution as evidence; after an
intervention the check rests ``REPAIR_COOLDOWN`` cycles.
"""

from __future__ import annotations

from typing import Any

from mira.shaping.attribution import (
    REPAIR_MIN_GAIN,
    REPAIR_MIN_SHARE,
    ReturnAttribution,
    attribute_returns,
    cv_r2,
)
from mira.shaping.decomposition import DECOMPOSE_RIDGE
from mira.shaping.factors import FactorSource
from mira.shaping.source import HarsReward
from mira.tasks.card import TaskCard

REPAIR_CYCLES = 3
"""Cycles in a row with a feature that explains the residual before SRR is called: a persistent gain,
not one noisy cross-validation."""
REPAIR_MIN_EPISODES = 10
"""Stored episodes needed before the attribution is measured (two per fold of its cross-validation). Few
enough that a flaw the random warm-up's episodes already show is repaired about when learning starts, before
the policy commits to what the flawed program pays for (a policy is slow to unlearn it after the repair)."""
REPAIR_MAX_EPISODES = 200
"""The attribution uses at most this many of the latest stored episodes (recent behaviour, bounded cost)."""
REPAIR_FOLDS = 5
"""Cross-validation folds of the attribution (each fold still spans the whole run, dealt round-robin)."""
REPAIR_COOLDOWN = 10
"""Cycles without a structural trigger after an intervention, accepted or not: as long as the monitor's
cooldown ``K_cool`` (Table 1), so that an edit has time to act before the next one."""


class StructuralCheck:
    """Measures the attribution each cycle and says when it warrants a repair."""

    def __init__(self, card: TaskCard, hars: HarsReward) -> None:
        self.card, self.hars = card, hars
        self.streak = 0
        self.cooldown = 0
        self.latest: ReturnAttribution | None = None

    def _episodes(self) -> tuple[list[Any], Any] | None:
        rows, returns = self.hars.memory.recent_episodes(REPAIR_MAX_EPISODES)
        if len(rows) < REPAIR_MIN_EPISODES:
            return None
        return rows, returns

    def observe(self) -> ReturnAttribution | None:
        """This cycle's attribution (None before enough episodes are stored); updates the streak."""
        found = self._episodes()
        self.cooldown = max(0, self.cooldown - 1)
        if found is None:
            self.latest = None
            self.streak = 0
            return None
        rows, returns = found
        memory = self.hars.memory
        sums, ranges = memory.feature_sums(rows, self.card.feature_values)
        self.latest = attribute_returns(memory.head_sums(rows), returns, sums, DECOMPOSE_RIDGE,
                                        REPAIR_FOLDS, ranges, centred=True, select=True)
        best = self.latest.best
        counts = best is not None and best.gain >= REPAIR_MIN_GAIN and best.share >= REPAIR_MIN_SHARE
        self.streak = self.streak + 1 if counts else 0
        return self.latest

    @property
    def triggered(self) -> bool:
        return self.streak >= REPAIR_CYCLES and self.cooldown == 0

    def rest(self) -> None:
        """An intervention happened (for whatever reason): let the next program be measured afresh."""
        self.streak = 0
        self.cooldown = REPAIR_COOLDOWN

    def explain(self, factors: FactorSource) -> float:
        """Out-of-sample R² of the stored returns decomposed over ``factors`` (SRR's return-explanation
        check; the same episodes and folds as the attribution)."""
        found = self._episodes()
        if found is None:
            return float("nan")
        rows, returns = found
        return cv_r2(self.hars.memory.head_sums(rows, factors), returns, DECOMPOSE_RIDGE,
                     REPAIR_FOLDS, centred=True, select=True)

    def state_dict(self) -> dict[str, Any]:
        return {"streak": self.streak, "cooldown": self.cooldown}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.streak, self.cooldown = int(state.get("streak", 0)), int(state.get("cooldown", 0))
