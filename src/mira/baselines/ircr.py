"""IRCR — the guidance reward of Gangwani, Zhou and Peng (2020), "Learning Guidance Rewards with
Trajectory-space Smoothing".

Definition (their section 3): the guidance reward of a state–action pair is the expected
*normalised* return of the stored trajectories that contain it; every transition of a trajectory
gets the same credit ("uniform redistribution"), and the agent (SAC in the paper) learns on it
instead of the delayed environmental reward. As their code (and the LaRe repository's IRCR) does it:

* **Credit per step**: a trajectory's credit is its per-step return R/T, min-max normalised,
  ``(R/T − m) / (M − m)``, with m and M the smallest and largest per-step returns of the trajectories
  the agent can be trained on (the buffer's and the heap's).
* **A heap of the best trajectories**: the ``heap_episodes`` trajectories with the highest R/T seen
  so far are kept, and ``heap_fraction`` (half) of every batch is drawn from them, the rest
  uniformly from the buffer's finished episodes. This is what makes the credit informative early:
  the best behaviour found is replayed with high credit next to everything else.

Ours:

* A continuous state–action pair occurs in one stored trajectory, so the expectation is that
  trajectory's credit, read from the return the replay buffer writes next to every row of a finished
  episode (``Batch.episode_return``).
* The heap holds row ranges of the one replay buffer rather than copies: a heap trajectory whose rows
  start to be overwritten leaves the heap (with the default buffer of 10⁶ steps, never within a run
  of up to 10⁶ steps). m and M are over the episodes still (at least partly) in the buffer, which
  include the heap's; a credit is clipped to [0, 1].
* While all stored per-step returns are equal (min = max, e.g. after one episode) every transition
  gets ``equal_credit`` (0.5 by default): normalisation is undefined then.
* No fitting loss exists; ``ircr_return_min`` / ``ircr_return_max`` (per step) are logged instead.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from mira.baselines.common import TrajectoryRewardSource
from mira.baselines.config import IRCRConfig
from mira.replay import Batch
from mira.rewards.base import RewardContext


class IRCRReward(TrajectoryRewardSource):
    """Guidance reward: the trajectory's per-step return, min-max normalised; half of each batch from
    a heap of the best trajectories."""

    name = "ircr"
    log_fields: ClassVar[tuple[str, ...]] = ("ircr_return_min", "ircr_return_max", "ircr_heap_min", "corr_dense")

    def __init__(self, config: IRCRConfig | None = None) -> None:
        self.config = config or IRCRConfig()
        if self.config.heap_episodes < 0 or not 0.0 <= self.config.heap_fraction <= 1.0:
            raise ValueError("ircr: heap_episodes must be >= 0 and heap_fraction in [0, 1]")
        super().__init__(max_episodes=self.config.max_episodes)
        self.r_min = 0.0
        self.r_max = 0.0
        self._stats: dict[str, torch.Tensor] = {}

    def bind(self, ctx: RewardContext) -> None:
        super().bind(ctx)
        self.heap_first = np.zeros(0, dtype=np.int64)  # the buffer's running count at each one's first step
        self.heap_length = np.zeros(0, dtype=np.int64)
        self.heap_score = np.zeros(0, dtype=np.float64)  # R/T
        self._refresh()

    # ----------------------------------------------------------------------------------- episodes
    def on_episode_end(self, rows: np.ndarray, episode_return: float) -> None:
        super().on_episode_end(rows, episode_return)
        store = self.store
        if len(store) and int(store.first[-1]) == self.ctx.buffer.total_added - len(rows):  # stored: whole
            self._offer(int(store.first[-1]), int(store.length[-1]), float(store.returns[-1]) / len(rows))
        self._refresh()

    def _offer(self, first: int, length: int, score: float) -> None:
        """Put an episode on the heap if it is among the ``heap_episodes`` best (ties: the older stays)."""
        if self.config.heap_episodes == 0:
            return
        first_a = np.append(self.heap_first, first)
        length_a = np.append(self.heap_length, length)
        score_a = np.append(self.heap_score, score)
        keep = np.argsort(-score_a, kind="stable")[: self.config.heap_episodes]
        keep.sort()
        self.heap_first, self.heap_length, self.heap_score = first_a[keep], length_a[keep], score_a[keep]

    def _prune_heap(self) -> None:
        """Drop heap trajectories whose first row has been overwritten."""
        buf = self.ctx.buffer
        intact = buf.total_added - self.heap_first <= buf.capacity
        if not intact.all():
            self.heap_first, self.heap_length, self.heap_score = (
                self.heap_first[intact], self.heap_length[intact], self.heap_score[intact])

    def _refresh(self) -> None:
        self.store.prune()
        self._prune_heap()
        if len(self.store):
            per_step = self.store.returns / np.maximum(self.store.length, 1)
            self.r_min, self.r_max = float(per_step.min()), float(per_step.max())
        heap_min = float(self.heap_score.min()) if self.heap_score.size else 0.0
        self._stats = {"ircr_return_min": torch.tensor(self.r_min), "ircr_return_max": torch.tensor(self.r_max),
                       "ircr_heap_min": torch.tensor(heap_min)}

    # ------------------------------------------------------------------------------- sampling
    def sample_rows(self, batch_size: int, rng: np.random.Generator) -> np.ndarray:
        n_heap = round(batch_size * self.config.heap_fraction) if self.heap_first.size else 0
        uniform = self.ctx.buffer.sample_indices(batch_size - n_heap, rng, completed_only=True)
        if n_heap == 0:
            return uniform
        pick = rng.integers(0, self.heap_first.size, size=n_heap)
        offset = (rng.random(n_heap) * self.heap_length[pick]).astype(np.int64)
        heap_rows = (self.heap_first[pick] + offset) % self.ctx.buffer.capacity
        return np.concatenate([uniform, heap_rows])

    # ---------------------------------------------------------------------------------- reward
    def credit(self, per_step_return: torch.Tensor) -> torch.Tensor:
        """Normalised credit in [0, 1] of trajectories with the given per-step returns R/T."""
        span = self.r_max - self.r_min
        if not span > 0.0:
            return torch.full_like(per_step_return, float(self.config.equal_credit))
        return ((per_step_return - self.r_min) / span).clamp(0.0, 1.0)

    def compute_reward(self, batch: Batch) -> torch.Tensor:
        lengths = torch.from_numpy(self._episode_lengths(batch.indices)).to(batch.episode_return.device)
        return self.credit(batch.episode_return.to(torch.float32) / lengths)

    def _episode_lengths(self, rows: np.ndarray) -> np.ndarray:
        """Length of the (finished) episode each row belongs to: its last step's index + 1, found from the
        row's own step index and the buffer's episode ids (episodes are contiguous in the ring)."""
        buf = self.ctx.buffer
        step = buf.episode_step[torch.from_numpy(rows)].numpy().astype(np.int64)
        written = buf.total_added - ((buf.pos - rows - 1) % buf.capacity + 1)  # running count the row was written at
        first = written - step
        idx = np.searchsorted(self.store.first, first)
        idx = np.minimum(idx, max(len(self.store) - 1, 0))
        found = (len(self.store) > 0) & (self.store.first[idx] == first)
        return np.where(found, self.store.length[idx], step + 1).astype(np.float32)

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        out = dict(self._stats)
        out.update(self.diagnostics(batch))
        return out

    def describe(self) -> dict[str, Any]:
        return {"method": self.name,
                "credit": "(R/T - min) / (max - min) over per-step returns of episodes in the buffer",
                "heap_episodes": self.config.heap_episodes, "heap_fraction": self.config.heap_fraction,
                "equal_credit": self.config.equal_credit}

    def state_dict(self) -> dict[str, Any]:
        return {**self.base_state(), "r_min": self.r_min, "r_max": self.r_max,
                "heap": {"first": self.heap_first.copy(), "length": self.heap_length.copy(),
                         "score": self.heap_score.copy()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.load_base_state(state)
        self.r_min, self.r_max = float(state["r_min"]), float(state["r_max"])
        heap = state.get("heap") or {"first": [], "length": [], "score": []}
        self.heap_first = np.asarray(heap["first"], dtype=np.int64).copy()
        self.heap_length = np.asarray(heap["length"], dtype=np.int64).copy()
        self.heap_score = np.asarray(heap["score"], dtype=np.float64).copy()
        self._refresh()
