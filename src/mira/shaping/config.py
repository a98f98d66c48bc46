"""Hyperparameters of HARS (section 4.2.2, Table 1).

This module imports nothing from MIRA so that :mod:`mira.config` can embed :class:`HarsConfig` in
``TrainConfig`` without an import cycle.
"""

from __future__ import annotations

from dataclasses import dataclass

DEFAULT_DECOMPOSED_KAPPA = 0.0
"""κ under ``decomposed`` alignment when ``shaping_weight`` is None: the agent learns from r̂ alone. A
potential of the returns' scale added to r̂ destabilises the critic where returns are large."""


@dataclass
class HarsConfig:
    """The inner-loop reward shaper: FAB (ϕ) → VPM (φ) potential, TCE (ψ) auxiliary, PBRS. Network sizes
    and loss weights are constants beside the code that uses them (:mod:`mira.shaping.networks`,
    :mod:`mira.shaping.objective`, :mod:`mira.shaping.decomposition`)."""

    alignment: str = "decomposed"
    """What Φ is TD-aligned to and what the agent's reward is built on. ``decomposed`` (default): the
    decomposition head's per-step r̂ (L_align's target r̂ + γ(1 − d)Φ(s′); agent reward
    r̂ + κ(γΦ(s′) − Φ(s))). ``episodic``: the paper's letter, the extrinsic episodic reward r_ext (0 on
    every step but the last) in both places; Φ then learns only how near the episode's end a state is,
    so it does not learn in the episodic setting."""
    shaping_weight: float | None = None
    """κ, the weight of the PBRS term γΦ(s′) − Φ(s) in the agent's reward. None: 1 under ``episodic``
    alignment (the paper), and under ``decomposed`` ``DEFAULT_DECOMPOSED_KAPPA``."""
    update_every: int = 8
    """Train (ϕ, φ, ψ) on every this many agent updates; every sampled batch is still shaped by the
    current Φ (one fixed function between two training steps, so a cycle's batches are shaped
    together). A training step costs about ten times the shaping of a batch. 1 = every update, as in
    Algorithm 3."""
    lr: float = 3e-4
    """Adam learning rate of the one optimiser over (ϕ, φ, ψ) (the field's usual 3e-4; Table 1: 1e-4)."""

    def kappa(self) -> float:
        """The PBRS weight κ in force (see ``shaping_weight``)."""
        if self.shaping_weight is not None:
            return float(self.shaping_weight)
        return 1.0 if self.alignment == "episodic" else DEFAULT_DECOMPOSED_KAPPA
