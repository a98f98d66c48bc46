"""From a method name (``lare``, ``rd``, ``ircr``, ``vib``) and a run's config to its reward source.

:data:`mira.methods.METHODS` calls :func:`build_baseline` lazily, so a ``dense`` run imports none of
this.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from mira.errors import UsageError

if TYPE_CHECKING:
    from mira.config import TrainConfig
    from mira.rewards.base import RewardSource
    from mira.tasks.card import TaskCard

BASELINES = ("lare", "rd", "ircr", "vib")


def build_baseline(method: str, config: TrainConfig, card: TaskCard, run_dir: Path) -> tuple[RewardSource, str]:
    """The reward source of baseline ``method`` (its parameters at their defaults, see
    :mod:`mira.baselines.config`) and a one-line description of it."""
    if method == "ircr":
        from mira.baselines.ircr import IRCRReward

        return IRCRReward(), (
            "IRCR: every transition credited with its trajectory's return, min-max normalised to [0, 1]")
    if method == "rd":
        from mira.baselines.rd import RDReward

        return RDReward(), (
            "RD: linear per-step reward on [s, a, a^2, 1], ridge least squares of returns on summed features")
    if method == "vib":
        from mira.baselines.vib import VIBReward

        vib = VIBReward()
        return vib, (
            f"VIB: Gaussian bottleneck encoder + reward decoder fitted by return decomposition ({vib.config.loss})")
    if method == "lare":
        from mira.baselines.lare import LaReReward, ProgramFactors, lare_program
        from mira.factors.compiler import InadmissibleCodeError

        program, origin = lare_program(card, Path(run_dir), config.llm, program_file=config.program, seed=config.seed)
        try:
            factors = ProgramFactors(program, card)
        except InadmissibleCodeError as exc:
            raise UsageError(f"lare: the latent-reward program is not admissible: {exc}") from exc
        names = ", ".join(factors.names)
        lare = LaReReward(factors, origin=origin)
        return lare, (
            f"LaRe: static LLM factor program ({names}) decoded to a per-step reward by return decomposition "
            f"({lare.config.loss})")
    raise UsageError(f"unknown baseline {method!r}; expected one of {', '.join(BASELINES)}")
