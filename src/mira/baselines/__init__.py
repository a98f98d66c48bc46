"""The paper's comparison baselines (section 5.1.2) as reward sources of the one trainer.

* :class:`~mira.baselines.ircr.IRCRReward`  — IRCR: normalised per-step return as uniform credit, half of
  each batch from a heap of the best trajectories.
* :class:`~mira.baselines.rd.RDReward`      — RD: linear reward, ridge least squares on trajectories.
* :class:`~mira.baselines.lare.LaReReward`  — LaRe: static LLM factor program + return-decomposition decoder.
* :class:`~mira.baselines.vib.VIBReward`    — VIB: information-bottleneck reward model + return decomposition.

All of them sample only finished episodes, read episodes from the replay buffer by row ranges
(:mod:`mira.rewards.episodes`), never read the dense reward for their reward (only :mod:`.diagnostics`
does, for the logged ``corr_dense``), and take their parameters as one dataclass each
(:mod:`mira.baselines.config`; a run uses the defaults). Each module's docstring says where ours differs
from its paper. Method builders live in :mod:`mira.methods.baselines`.
"""
