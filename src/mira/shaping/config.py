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
    """The inner-loop reward shaper: FAB (ϕ) → VPM (φ) potential, TCE (ψ) auxiliary, PBRS."""

    alignment: str = "decomposed"
    """What Φ is TD-aligned to and what the agent's reward is built on. ``decomposed`` (default): the
    decomposition head's per-step r̂ (L_align's target r̂ + γ(1 − d)Φ(s′); agent reward
    r̂ + κ(γΦ(s′) − Φ(s))). ``episodic``: the paper's letter, the extrinsic episodic reward r_ext (0 on
    every step but the last) in both places; Φ then learns only how near the episode's end a state is,
    so it does not learn in the episodic setting."""
    shaping_weight: float | None = None
    """κ, the weight of the PBRS term γΦ(s′) − Φ(s) in the agent's reward. None: 1 under ``episodic``
    alignment (the paper), and under ``decomposed`` ``DEFAULT_DECOMPOSED_KAPPA``."""
    decompose_phi_at: str = "next"
    """Where the decomposition head reads PHI factors: ``next`` (s′, the state the step's reward was
    earned into), ``state`` (s) or ``both``. AUX factors are always read at (s, a)."""
    decompose_ridge: float = 1.0
    """Ridge weight of the head's episode-sum regression, in standardised units (one pseudo-episode): the
    ridge itself, or with ``decompose_ridge_select`` the largest the selection may choose."""
    decompose_ridge_select: bool = True
    """Choose the ridge at each fit among ``decompose_ridge · 10⁻ᵏ`` (k = 0 … 6) by leave-one-episode-out
    error, so that it fades as the episodes pin the weights down. Summed over an episode, a program's
    factors are nearly collinear (effort, posture and the bias move with speed); a fixed ridge moves
    weight along that direction (a control cost fitted as a bonus), while the selected one lets the
    returns decide and recovers the task's own weights. False:
    the fixed ``decompose_ridge``."""
    decompose_ridge_centred: bool = True
    """Scale each feature's ridge penalty by its variance across episodes rather than its mean square
    (uncentred, a feature with a large mean and little spread — a control cost, the bias — is shrunk
    by its size, not by the evidence). False with ``decompose_ridge_select`` False: the head before
    either switch, bit for bit."""
    decompose_nonneg: bool = False
    """Constrain the head's factor weights to w ≥ 0 (the bias stays free): a weight can scale a factor or
    drop it, never turn what the program declares a penalty into a bonus. Off: unconstrained ridge."""
    decompose_min_episodes: int = 2
    """Finished episodes needed before the head's first fit (r̂ is 0 until then)."""
    decompose_max_episodes: int = 5_000
    """Episodes whose summed features the head keeps (oldest dropped first)."""
    align_weight: float = 1.0
    """λ of eq. (10): weight of the TD alignment loss L_align (Table 1)."""
    aux_weight: float = 0.1
    """μ of eq. (10): weight of the TCE temporal-consistency loss L_aux (Table 1)."""
    terminal_weight: float = 0.1
    """η of eq. (11): penalty η·E[Φ(s_T)²] on true terminal states (the paper only asks η > 0)."""
    entropy_weight: float = 1e-3
    """Weight of the attention-entropy regulariser (maximises H(α) against premature collapse)."""
    d_z: int = 64
    """Factor embedding dimension d_z of the FAB (Table 1)."""
    id_dim: int = 16
    """Dimension of the learned per-name factor-ID embedding."""
    id_slots: int = 64
    """Initial rows of the name → ID-embedding table (grows on re-initialisation when exceeded)."""
    fab_hidden: int = 64
    """Hidden width of the per-factor embedder g_ϕ."""
    query_hidden: int = 64
    """Hidden width of the state query Q_ϕ(s)."""
    tce_hidden: int = 128
    """GRU hidden size of the Temporal Context Encoder (Table 1)."""
    tce_window: int = 8
    """Window length of consecutive same-episode steps the TCE sees (the last one is the target)."""
    tce_batch: int | None = 32
    """Sampled rows whose windows feed L_aux when it is computed (None: the whole batch)."""
    tce_every: int = 4
    """Compute L_aux (and step ψ) on every this many HARS training steps: the GRU is a chain of small
    sequential ops, and a sample of windows every few steps keeps the auxiliary signal at a fraction of
    the cost. 1 = every training step, as in Algorithm 3."""
    update_every: int = 8
    """Train (ϕ, φ, ψ) on every this many agent updates; every sampled batch is still shaped by the
    current Φ (one fixed function between two training steps, so a cycle's batches are shaped
    together). A training step costs about ten times the shaping of a batch. 1 = every update, as in
    Algorithm 3."""
    train_in_background: bool | None = None
    """Run each training step of (ϕ, φ, ψ) and each cycle's no-grad shaping pass on a second thread
    beside the agent's updates. The step lands at the next training update either way, so the run is
    the same computation, bit for bit, whatever this is. None (default): on when a core is free for it
    (the process may use more cores than PyTorch's intra-op threads, and the load average leaves one
    idle; otherwise the thread would wait for a core, or take one from another run); False: everything
    on the caller's thread."""
    vpm_hidden: int = 128
    """Width of the two hidden layers of the Value Potential Mapping MLP (Table 1)."""
    vpm_state_proj: bool = False
    """Concatenate a learned state projection with v before the VPM ("optionally", section 4.2.2)."""
    state_proj_dim: int = 32
    """Width of that state projection (used only with ``vpm_state_proj``)."""
    lr: float = 3e-4
    """Adam learning rate of the one optimiser over (ϕ, φ, ψ) (the field's usual 3e-4; Table 1: 1e-4)."""
    max_grad_norm: float | None = None
    """Clip the joint gradient of (ϕ, φ, ψ) to this norm before the step (None: no clipping)."""
    joint: bool = True
    """Eq. (10): let the critic's loss flow into (ϕ, φ) through the shaped reward. False: Φ is
    trained by L_align (+ regularisers) only and the agent sees a constant (detached) reward."""
    return_scale: bool = True
    """Learn Φ in units of the typical episodic return: Φ(s) = σ_R · Φ̂(s), with σ_R the root mean
    square of recent episodic returns (at least 1), and the alignment and joint losses measured in
    those units. Adam moves weights by about the learning rate per step whatever the gradient's size,
    so without it a potential that must reach returns of 10^4-10^5 (HumanoidStandup) would need
    millions of updates to get there; with it Φ̂ stays of order one on every task. A slowly moving
    σ_R is just part of Φ's own learning. False: Φ is the network's raw output."""
    return_scale_ema: float = 0.05
    """Rate of the exponential average of squared episodic returns behind σ_R."""
    input_clip: float = 10.0
    """Normalised factor values and observations are clipped to ±this before entering the networks."""
    recompute_chunk: int = 65_536
    """Rows per vectorised pass of ``recompute_all`` (factor re-evaluation after a program change)."""

    def kappa(self) -> float:
        """The PBRS weight κ in force (see ``shaping_weight``)."""
        if self.shaping_weight is not None:
            return float(self.shaping_weight)
        return 1.0 if self.alignment == "episodic" else DEFAULT_DECOMPOSED_KAPPA
