"""The reward-source interface: how every method (dense, sparse, HARS, MIRA, LaRe, RD, IRCR, VIB)
plugs into the one trainer.

The trainer stores transitions with the *extrinsic* reward the agent may see (episodic: 0 except at
an episode's last step), samples a batch, asks the reward source to **relabel** it, hands the
relabelled reward to the agent's update, and then lets the source **update** its own parameters.
Sources that fit per-step rewards from trajectories learn from the episodes the trainer reports.
A source that wants the critic's loss to flow into its parameters returns a reward tensor that
requires grad; the agent backpropagates through it and the source steps its own optimiser in
``update`` (that is how HARS's joint objective works without the loop knowing about it).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch

from mira.replay import Batch, ReplayBuffer
from mira.tasks.card import TaskCard


@dataclass
class RewardContext:
    """What the trainer hands a reward source once, before training starts."""

    card: TaskCard
    obs_dim: int
    act_dim: int
    gamma: float
    device: torch.device
    buffer: ReplayBuffer
    seed: int
    run_dir: Path


class RewardSource:
    """Base class with no-op hooks; subclasses override what they need."""

    name: ClassVar[str] = "base"
    needs_complete_episodes: ClassVar[bool] = False
    """Sample only transitions whose episode has ended (trajectory-level credit needs the return)."""

    def bind(self, ctx: RewardContext) -> None:
        self.ctx = ctx

    def on_transition(self, row: int) -> None:
        """A transition was stored at buffer row ``row``."""

    def on_episode_end(self, rows: np.ndarray, episode_return: float) -> None:
        """An episode ended; ``rows`` are its buffer rows (oldest first) and its extrinsic return."""

    def sample_rows(self, batch_size: int, rng: np.random.Generator) -> np.ndarray:
        """Buffer rows of the next batch: uniform over the buffer (over finished episodes when
        :attr:`needs_complete_episodes`). A method whose sampling is part of it (IRCR) overrides this."""
        return self.ctx.buffer.sample_indices(batch_size, rng, self.needs_complete_episodes)

    def relabel(self, batch: Batch) -> torch.Tensor:
        """The per-transition reward ``[B]`` the agent learns from."""
        raise NotImplementedError

    def update(self, batch: Batch, step: int) -> dict[str, torch.Tensor]:
        """Fit the source's own parameters after the agent's update; returns loggable scalars."""
        return {}

    def close(self) -> None:
        """Training is over: finish any work in flight and release threads or processes (may be reused after)."""

    def describe(self) -> dict[str, Any]:
        """Facts about the source recorded in the run directory."""
        return {"method": self.name}

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        return None


class DenseReward(RewardSource):
    """Oracle: the environment's own per-step (dense) reward, the performance ceiling."""

    name = "dense"

    def relabel(self, batch: Batch) -> torch.Tensor:
        idx = torch.from_numpy(batch.indices)
        return self.ctx.buffer.dense_reward[idx].to(batch.reward.device)


class SparseReward(RewardSource):
    """The episodic reward as delivered: the episode's return at its last step, 0 elsewhere."""

    name = "sparse"

    def relabel(self, batch: Batch) -> torch.Tensor:
        return batch.reward
