"""Configuration of MIRA's outer loop (kept import-light so that ``mira.config`` can embed it)."""

from __future__ import annotations

from dataclasses import dataclass, field

from mira.mcm.config import MCMConfig
from mira.srr.config import SRRConfig


@dataclass
class OuterLoopConfig:
    """MIRA's outer loop: evidence collection and the structural-repair switch (the ablation, ``full``,
    ``no-mcm`` or ``no-srr``, follows from the method name)."""

    holdout_episodes: int = 2
    """Held-out episodes rolled out with the frozen policy each cycle (D̃_k)."""
    repair: bool = True
    """Also call SRR on evidence of a structural flaw: a task feature that, cycle after cycle, explains
    episodic returns the program's factors cannot (:mod:`mira.shaping.attribution`). False: SRR is called by
    the monitor's own triggers only (its anomaly score, and the plateau detector on cards with a
    ``band_feature``), as in the paper."""
    mcm: MCMConfig = field(default_factory=MCMConfig)
    """Monitor hyperparameters (ΔT = ``mcm.delta_t`` is the cycle length)."""
    srr: SRRConfig = field(default_factory=SRRConfig)
    """Reframer hyperparameters."""
