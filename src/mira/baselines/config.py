"""Hyperparameters of the trajectory-feedback baselines (LaRe, RD, IRCR, VIB).

Plain dataclasses with no heavy imports: :mod:`mira.config` embeds :class:`BaselinesConfig` in every
run's ``TrainConfig`` (field ``baselines``), so ``config.json`` records them and ``--resume`` rebuilds
them. Only the method that runs reads its own section.

Defaults follow the papers where they say something and are chosen for cost otherwise: decoders are
small MLPs (2×128) refitted on every environment step once learning has started, on a batch of
4 episodes drawn from the replay buffer, with RRD's randomized-subsequence estimator (K = 64 steps
per episode, Ren et al. 2022's default), so a fit costs about one agent update.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class IRCRConfig:
    """IRCR (Gangwani et al. 2020): uniform credit of the normalised per-step return, half of each batch
    from a heap of the best trajectories."""

    heap_episodes: int = 10
    """How many of the best trajectories (by per-step return R/T) the heap keeps."""
    heap_fraction: float = 0.5
    """Fraction of every batch drawn from the heap's trajectories (the rest uniformly from the buffer)."""
    equal_credit: float = 0.5
    """Credit given to every transition while all stored returns are equal (min = max): normalisation
    is undefined then, and a constant says nothing about which behaviour is better."""
    max_episodes: int = 100_000
    """Bound on the episodes whose returns are tracked for min/max (oldest dropped first); episodes
    whose rows have all been overwritten in the replay buffer are dropped earlier."""


@dataclass
class RDConfig:
    """Return decomposition with a linear reward (Efroni et al. 2021): ridge regression of returns on
    summed features φ(s, a) = [s, a, a², 1]."""

    ridge: float = 1.0
    """Ridge weight on summed features standardised to unit mean square over the stored episodes: the
    penalty is ``ridge * diag(ΦᵀΦ) / n`` (n episodes), so 1.0 weighs like one pseudo-episode pulling every
    weight to 0 and washes out as episodes accumulate; a tiny absolute jitter keeps it solvable."""
    refit_every_episodes: int = 1
    """Re-solve the least-squares problem after every this many completed episodes."""
    min_episodes: int = 2
    """Episodes needed before the first fit (the reward is 0 until then)."""
    max_episodes: int = 5_000
    """Bound on the per-episode summed features kept (oldest dropped first); O(feature dim) each."""


@dataclass
class DecoderConfig:
    """How a neural per-step reward model is fitted to episodic returns (shared by LaRe and VIB)."""

    hidden: tuple[int, ...] = (128, 128)
    """Hidden widths of the MLP (ReLU)."""
    lr: float = 3e-4
    """Adam learning rate."""
    fit_every: int = 1
    """Take ``fit_iters`` gradient steps every this many environment steps (after learning starts)."""
    fit_iters: int = 1
    """Gradient steps per fit."""
    episodes_per_batch: int = 4
    """Complete episodes per gradient step, sampled uniformly from those still whole in the buffer
    (4 × K=64 = 256 transitions per step, an agent-sized batch)."""
    loss: str = "rrd"
    """``rrd``: randomized return decomposition (K random steps of an episode, their sum scaled by T/K
    regressed on the return); ``full``: every step of the episode (RD's full-trajectory loss)."""
    subseq_len: int = 64
    """K, steps sampled per episode by the ``rrd`` loss (all steps when an episode is shorter)."""
    min_episodes: int = 1
    """Complete, intact episodes needed before fitting starts."""
    max_episodes: int = 100_000
    """Bound on the episodes indexed for sampling (oldest dropped first); only row ranges are kept."""


@dataclass
class LaReConfig(DecoderConfig):
    """LaRe (Qu et al. 2025): a static LLM-written factor program, decoded to a per-step reward."""

    max_attempts: int = 3
    """LLM requests allowed to get an admissible program; each retry shows the LLM its previous reply
    and why it was rejected (LaRe's self-verification). The ``offline`` engineer needs one."""
    sandbox: bool = True
    """Also run the sandbox realizability check on real states before accepting the program."""


@dataclass
class VIBConfig(DecoderConfig):
    """Variational information bottleneck (Alemi et al. 2017) reward model fitted by return decomposition."""

    latent_dim: int = 16
    """Dimension of the Gaussian latent z."""
    beta: float = 1e-3
    """Weight of KL(q(z|s,a) ‖ N(0, I)) per step against the (normalised) return-regression loss."""
    decoder_hidden: tuple[int, ...] = (64,)
    """Hidden widths of the decoder z → reward (the encoder uses ``hidden``)."""


@dataclass
class BaselinesConfig:
    """Settings of the paper's comparison baselines (section 5.1.2); each method reads its own section."""

    lare: LaReConfig = field(default_factory=LaReConfig)
    """LaRe: LLM factor program + reward decoder."""
    rd: RDConfig = field(default_factory=RDConfig)
    """RD: linear reward by least squares on trajectories."""
    ircr: IRCRConfig = field(default_factory=IRCRConfig)
    """IRCR: normalised-return guidance reward."""
    vib: VIBConfig = field(default_factory=VIBConfig)
    """VIB: stochastic bottleneck encoder + reward decoder."""
    log_corr_dense: bool = True
    """Log ``corr_dense``, the Pearson correlation of the method's reward with the hidden dense reward
    on each sampled batch. Diagnostics only: it never feeds any reward."""
