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
    band_feature: str | None = None
    """Feature whose held-out values locate a stagnation band (default: the task card's ``band_feature``)."""
    mcm: MCMConfig = field(default_factory=MCMConfig)
    """Monitor hyperparameters (ΔT = ``mcm.delta_t`` is the cycle length)."""
    srr: SRRConfig = field(default_factory=SRRConfig)
    """Reframer hyperparameters."""
