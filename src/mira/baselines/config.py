"""Hyperparameters of the trajectory-feedback baselines (LaRe, RD, IRCR, VIB).

One plain dataclass per method, the documented constructor parameters of its reward class (as
keyword arguments are for a library's algorithms). They are not part of a run's ``TrainConfig``: a
``mira train`` run builds every baseline with these defaults (:mod:`mira.methods.baselines`).

Defaults follow the papers where they say something and are chosen for cost otherwise: decoders are
small MLPs (2×128) refitted on every environment step once learning has started, on a batch of
4 episodes drawn from the replay buffer, with RRD's randomized-subsequence estimator (K = 64 steps
per episode, Ren et al. 2022's default), so a fit costs about one agent update.
"""

from __future__ import annotations

from dataclasses import dataclass


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
    """LaRe (Qu et al. 2025): a static LLM-written factor program, decoded to a per-step reward.

    Only the decoder is configured here; the program is requested with the run's ``llm`` settings
    (``llm.followups`` + 1 requests at most) and always passes the static and sandbox checks."""


@dataclass
class VIBConfig(DecoderConfig):
    """Variational information bottleneck (Alemi et al. 2017) reward model fitted by return decomposition."""

    latent_dim: int = 16
    """Dimension of the Gaussian latent z."""
    beta: float = 1e-3
    """Weight of KL(q(z|s,a) ‖ N(0, I)) per step against the (normalised) return-regression loss."""
    decoder_hidden: tuple[int, ...] = (64,)
    """Hidden widths of the decoder z → reward (the encoder uses ``hidden``)."""
