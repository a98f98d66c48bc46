"""IRCR — the guidance reward of Gangwani, Zhou and Peng (2020), "Learning Guidance Rewards with
Trajectory-space Smoothing".

Definition (their section 3): the guidance reward of a state–action pair is the expected
*normalised* return of the stored trajectories that contain it,
``r_g(s, a) = E_{τ ∋ (s,a)} [(R(τ) − R_min) / (R_max − R_min)]``, with R_min and R_max the smallest and
largest returns of the trajectories in the replay buffer; the agent (SAC in the paper) learns on
``r_g`` instead of the delayed environmental reward. Every transition of a trajectory therefore gets
the same credit: its trajectory's normalised return ("uniform redistribution").

Ours:

* In continuous spaces a state–action pair occurs in one stored trajectory, so the expectation is
  that trajectory's normalised return — exactly what IRCR computes in practice. It is read from the
  return the replay buffer writes next to every row of a finished episode (``Batch.episode_return``).
* R_min and R_max are over the episodes whose rows are still (at least partly) in the buffer, kept
  as a small store of returns and pruned as the ring buffer overwrites rows; they are refreshed at
  each episode end. A credit is clipped to [0, 1] (a row of an episode that has just been pruned from
  the min/max window could otherwise fall slightly outside).
* While all stored returns are equal (min = max, e.g. after one episode) every transition gets
  ``equal_credit`` (0.5 by default): normalisation is undefined and any constant carries the same
  (lack of) information.
* No fitting loss exists; ``ircr_return_min`` / ``ircr_return_max`` are logged instead.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from mira.baselines.common import TrajectoryRewardSource
from mira.baselines.config import IRCRConfig
from mira.replay import Batch


class IRCRReward(TrajectoryRewardSource):
    """Guidance reward: the sampled transition's trajectory return, min-max normalised over the buffer."""

    name = "ircr"
    log_fields: ClassVar[tuple[str, ...]] = ("ircr_return_min", "ircr_return_max", "corr_dense")

    def __init__(self, config: IRCRConfig | None = None, *, log_corr_dense: bool = True) -> None:
        self.config = config or IRCRConfig()
        super().__init__(max_episodes=self.config.max_episodes, log_corr_dense=log_corr_dense)
        self.r_min = 0.0
        self.r_max = 0.0
        self._stats = {"ircr_return_min": torch.tensor(0.0), "ircr_return_max": torch.tensor(0.0)}

    def on_episode_end(self, rows: np.ndarray, episode_return: float) -> None:
        super().on_episode_end(rows, episode_return)
        self._refresh()

    def _refresh(self) -> None:
        rng = self.store.return_range()
        if rng is not None:
            self.r_min, self.r_max = rng
        self._stats = {"ircr_return_min": torch.tensor(self.r_min), "ircr_return_max": torch.tensor(self.r_max)}

    def credit(self, episode_return: torch.Tensor) -> torch.Tensor:
        """Normalised credit in [0, 1] of trajectories with the given returns."""
        span = self.r_max - self.r_min
        if not span > 0.0:
            return torch.full_like(episode_return, float(self.config.equal_credit))
        return ((episode_return - self.r_min) / span).clamp(0.0, 1.0)

    def compute_reward(self, batch: Batch) -> torch.Tensor:
        return self.credit(batch.episode_return.to(torch.float32))

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        out = dict(self._stats)
        out.update(self.diagnostics(batch))
        return out

    def describe(self) -> dict[str, Any]:
        return {"method": self.name, "credit": "(R - R_min) / (R_max - R_min) over episodes in the buffer",
                "equal_credit": self.config.equal_credit}

    def state_dict(self) -> dict[str, Any]:
        return {**self.base_state(), "r_min": self.r_min, "r_max": self.r_max}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.load_base_state(state)
        self.r_min, self.r_max = float(state["r_min"]), float(state["r_max"])
        self._refresh()
