"""Configuration of MIRA's outer loop (kept import-light so that ``mira.config`` can embed it)."""

from __future__ import annotations

from dataclasses import dataclass, field

from mira.mcm.config import MCMConfig
from mira.srr.config import SRRConfig


@dataclass
class OuterLoopConfig:
    """MIRA's outer loop: monitoring cadence, evidence collection and the ablation switches."""

    mode: str = "full"
    """``full`` (MCM + SRR), ``no-mcm`` (periodic, unguided SRR) or ``no-srr`` (diagnosis only)."""
    holdout_episodes: int = 2
    """Held-out episodes rolled out with the frozen policy each cycle (D̃_k)."""
    holdout_max_states: int = 1000
    """At most this many held-out states enter the diagnostics (evenly subsampled)."""
    periodic_cycles: int = 10
    """no-mcm: call SRR every this many cycles."""
    periodic_max: int = 5
    """no-mcm: at most this many periodic interventions (match MIRA's median trigger count)."""
    repair: bool = True
    """Also call SRR on evidence of a structural flaw: a task feature that, cycle after cycle, explains
    episodic returns the program's factors cannot (:mod:`mira.shaping.attribution`). False: the monitor's
    anomaly trigger only, as in the paper."""
    repair_min_gain: float = 0.05
    """Out-of-sample R² of the returns a feature must add to the program's for a cycle to count."""
    repair_min_share: float = 0.75
    """Fraction of what the program leaves unexplained (1 − its out-of-sample R²) that gain must cover.
    A missing factor, a loophole proxy or a misplaced gate leaves a residual that one task feature
    explains almost entirely; a feature that merely correlates with a skill the agent is acquiring (a
    gait angle) explains part of it."""
    repair_cycles: int = 3
    """Cycles in a row with such a feature before SRR is called."""
    repair_min_episodes: int = 10
    """Stored episodes needed before the attribution is measured (two per fold of its cross-validation).
    Few enough that a flaw the random warm-up's episodes already show is repaired about when learning
    starts, before the policy commits to what the flawed program pays for (a policy that has learned
    what a flaw pays for is slow to unlearn it after the repair)."""
    repair_max_episodes: int = 200
    """The attribution uses at most this many of the latest stored episodes."""
    repair_folds: int = 5
    """Cross-validation folds of the attribution."""
    repair_cooldown: int = 10
    """Cycles without a structural trigger after an intervention, accepted or not."""
    band_feature: str | None = None
    """Feature whose held-out values locate a stagnation band (default: the task card's ``band_feature``)."""
    mcm: MCMConfig = field(default_factory=MCMConfig)
    """Monitor hyperparameters (ΔT = ``mcm.delta_t`` is the cycle length)."""
    srr: SRRConfig = field(default_factory=SRRConfig)
    """Reframer hyperparameters."""
