"""The one replay buffer shared by every agent and reward source.

It stores both observations, the action, the extrinsic reward the agent is allowed to see (episodic
in sparse methods), the environment's dense reward (for the oracle and for diagnostics only, never
part of a sampled :class:`Batch`), termination and truncation separately (a truncation is not a
terminal for bootstrapping), and the episode id and in-episode step of every transition. When an
episode ends its return is written next to each of its transitions, which is what trajectory-level
reward sources (IRCR, RD, LaRe, VIB) need, so no second buffer exists.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


@dataclass
class Batch:
    """A sampled minibatch. ``reward`` is the extrinsic reward the agent may see; reward sources
    relabel it. ``indices`` are buffer rows, for sources that keep per-transition columns."""

    obs: torch.Tensor
    action: torch.Tensor
    next_obs: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    episode_id: torch.Tensor
    episode_return: torch.Tensor
    indices: np.ndarray

    def to(self, device: torch.device) -> Batch:
        if device.type == "cpu":
            return self
        return Batch(
            obs=self.obs.to(device, non_blocking=True),
            action=self.action.to(device, non_blocking=True),
            next_obs=self.next_obs.to(device, non_blocking=True),
            reward=self.reward.to(device, non_blocking=True),
            terminated=self.terminated.to(device, non_blocking=True),
            truncated=self.truncated.to(device, non_blocking=True),
            episode_id=self.episode_id.to(device, non_blocking=True),
            episode_return=self.episode_return.to(device, non_blocking=True),
            indices=self.indices,
        )


class ReplayBuffer:
    """Ring buffer of transitions with episode bookkeeping."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int) -> None:
        if capacity <= 0:
            raise ValueError("replay capacity must be positive")
        self.capacity = capacity
        self.obs_dim = obs_dim
        self.act_dim = act_dim
        self.obs = torch.zeros((capacity, obs_dim), dtype=torch.float32)
        self.next_obs = torch.zeros((capacity, obs_dim), dtype=torch.float32)
        self.action = torch.zeros((capacity, act_dim), dtype=torch.float32)
        self.reward = torch.zeros(capacity, dtype=torch.float32)
        self.dense_reward = torch.zeros(capacity, dtype=torch.float32)
        self.terminated = torch.zeros(capacity, dtype=torch.float32)
        self.truncated = torch.zeros(capacity, dtype=torch.float32)
        self.episode_id = torch.zeros(capacity, dtype=torch.int64)
        self.episode_step = torch.zeros(capacity, dtype=torch.int64)
        self.episode_return = torch.full((capacity,), float("nan"), dtype=torch.float32)
        self.pos = 0
        self.size = 0
        self.total_added = 0
        self.open_episode_len = 0  # transitions of the episode still running (its return unknown)

    def add(
        self,
        obs: np.ndarray,
        action: np.ndarray,
        reward: float,
        dense_reward: float,
        next_obs: np.ndarray,
        terminated: bool,
        truncated: bool,
        episode_id: int,
    ) -> int:
        """Store one transition; returns its row."""
        row = self.pos
        self.obs[row] = torch.from_numpy(np.asarray(obs, dtype=np.float32))
        self.next_obs[row] = torch.from_numpy(np.asarray(next_obs, dtype=np.float32))
        self.action[row] = torch.from_numpy(np.asarray(action, dtype=np.float32))
        self.reward[row] = reward
        self.dense_reward[row] = dense_reward
        self.terminated[row] = float(terminated)
        self.truncated[row] = float(truncated)
        self.episode_id[row] = episode_id
        self.episode_step[row] = self.open_episode_len
        self.episode_return[row] = float("nan")
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)
        self.total_added += 1
        self.open_episode_len += 1
        return row

    def episode_rows(self, length: int | None = None) -> np.ndarray:
        """Rows of the most recent ``length`` transitions (default: the open episode), oldest first."""
        n = self.open_episode_len if length is None else length
        n = min(n, self.size)
        return (self.pos - n + np.arange(n)) % self.capacity

    def finish_episode(self, episode_return: float) -> np.ndarray:
        """Record the return of the episode that just ended next to its transitions; returns its rows."""
        rows = self.episode_rows()
        self.episode_return[torch.from_numpy(rows)] = float(episode_return)
        self.open_episode_len = 0
        return rows

    def truncate_open_episode(self, episode_return: float) -> np.ndarray:
        """End the open episode at its last stored transition, as a time limit would have: that
        transition becomes truncated and carries the episodic reward (``episode_return``, the sum so far);
        returns the episode's rows (see :meth:`finish_episode`). For a run stopped mid-episode."""
        if self.open_episode_len == 0:
            return np.zeros(0, dtype=np.int64)
        last = (self.pos - 1) % self.capacity
        self.truncated[last] = 1.0
        self.reward[last] = float(episode_return)
        return self.finish_episode(episode_return)

    @property
    def completed_size(self) -> int:
        """Number of stored transitions whose episode has ended."""
        return max(0, self.size - self.open_episode_len)

    def sample_indices(self, batch_size: int, rng: np.random.Generator, completed_only: bool = False) -> np.ndarray:
        if completed_only:
            n = self.completed_size
            if n == 0:
                raise ValueError("no completed episode in the buffer yet")
            back = rng.integers(0, n, size=batch_size)
            return (self.pos - self.open_episode_len - 1 - back) % self.capacity
        return rng.integers(0, self.size, size=batch_size)

    def gather(self, indices: np.ndarray) -> Batch:
        idx = torch.from_numpy(indices)
        return Batch(
            obs=self.obs[idx],
            action=self.action[idx],
            next_obs=self.next_obs[idx],
            reward=self.reward[idx],
            terminated=self.terminated[idx],
            truncated=self.truncated[idx],
            episode_id=self.episode_id[idx],
            episode_return=self.episode_return[idx],
            indices=indices,
        )

    def sample(self, batch_size: int, rng: np.random.Generator, completed_only: bool = False) -> Batch:
        return self.gather(self.sample_indices(batch_size, rng, completed_only))

    def state_dict(self) -> dict[str, Any]:
        n = self.size
        cols = ("obs", "next_obs", "action", "reward", "dense_reward", "terminated", "truncated",
                "episode_id", "episode_step", "episode_return")
        state: dict[str, Any] = {c: getattr(self, c)[:n].clone() for c in cols}
        state.update(pos=self.pos, size=self.size, total_added=self.total_added,
                     open_episode_len=self.open_episode_len, capacity=self.capacity)
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a saved buffer; a larger capacity is allowed (a run extended to a larger budget) while the
        saved ring has never wrapped, so every row keeps its index and the rows stay in order."""
        n, saved_cap = state["size"], state["capacity"]
        if saved_cap != self.capacity:
            never_wrapped = state["total_added"] == n and state["pos"] in (n, n % saved_cap)
            if saved_cap > self.capacity or not never_wrapped:
                raise ValueError(f"checkpoint buffer capacity {saved_cap} != configured {self.capacity} "
                                 "(a buffer can only grow, and only before its ring has wrapped)")
            state = {**state, "pos": n}
        for col in ("obs", "next_obs", "action", "reward", "dense_reward", "terminated", "truncated",
                    "episode_id", "episode_step", "episode_return"):
            getattr(self, col)[:n] = state[col]
        self.pos, self.size = state["pos"], n
        self.total_added, self.open_episode_len = state["total_added"], state["open_episode_len"]
