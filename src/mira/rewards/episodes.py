"""Complete episodes as row ranges of the one replay buffer (no second buffer).

The trainer reports every finished episode with its buffer rows (``on_episode_end``). The rows of an
episode are contiguous modulo the ring's capacity, so an episode is remembered by three numbers: the
buffer's running transition count at its first step (``first``; its first row is
``first % capacity``), its length and its return. Nothing else is copied.

The ring buffer overwrites its oldest rows first, so episodes go stale in the order they were stored:

* *intact*: none of its rows has been overwritten (``total_added - first <= capacity``). Only intact
  episodes are sampled for return decomposition — a partly overwritten episode no longer holds the
  transitions its return was earned with.
* *present*: at least its last row is still there. IRCR tracks min/max over these, because the
  sampler can still draw their surviving rows.

Episodes that were never wholly in the buffer (longer than its capacity) are not stored at all.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mira.replay import ReplayBuffer


class EpisodeStore:
    """Row ranges, lengths and returns of completed episodes, oldest first, pruned as rows are reused."""

    def __init__(self, buffer: ReplayBuffer, max_episodes: int = 100_000) -> None:
        if max_episodes <= 0:
            raise ValueError("max_episodes must be positive")
        self.buffer = buffer
        self.max_episodes = int(max_episodes)
        self.first = np.zeros(0, dtype=np.int64)
        self.length = np.zeros(0, dtype=np.int64)
        self.returns = np.zeros(0, dtype=np.float64)
        self.rejected = 0

    # ------------------------------------------------------------------------------- bookkeeping
    def __len__(self) -> int:
        return int(self.first.shape[0])

    def add(self, rows: np.ndarray, episode_return: float) -> bool:
        """Remember the episode that just ended at ``rows``; False (and not stored) if it is not whole."""
        buf = self.buffer
        n = len(rows)
        first = buf.total_added - n
        whole = (
            n > 0
            and n <= buf.capacity
            and int(rows[0]) == first % buf.capacity
            and int(buf.episode_step[int(rows[0])]) == 0
            and int(buf.episode_step[int(rows[-1])]) == n - 1
            and int(buf.episode_id[int(rows[0])]) == int(buf.episode_id[int(rows[-1])])
            and np.isfinite(episode_return)
        )
        if not whole:
            self.rejected += 1
            self.prune()
            return False
        self.first = np.append(self.first, first)
        self.length = np.append(self.length, n)
        self.returns = np.append(self.returns, float(episode_return))
        self.prune()
        return True

    def prune(self) -> int:
        """Drop episodes none of whose rows remain, and the oldest beyond ``max_episodes``; returns #dropped."""
        total, cap = self.buffer.total_added, self.buffer.capacity
        last = self.first + self.length - 1
        # Gone episodes form a prefix (the ring overwrites oldest first), so counting them finds it.
        keep_from = int(np.count_nonzero(total - last > cap))
        keep_from = max(keep_from, len(self) - self.max_episodes)
        if keep_from > 0:
            self.first, self.length, self.returns = (
                self.first[keep_from:], self.length[keep_from:], self.returns[keep_from:]
            )
        return keep_from

    def intact_start(self) -> int:
        """Index of the oldest episode none of whose rows has been overwritten (all later ones are intact)."""
        total, cap = self.buffer.total_added, self.buffer.capacity
        return int(np.searchsorted(self.first, total - cap, side="left"))

    def n_intact(self) -> int:
        return len(self) - self.intact_start()

    def start_rows(self, idx: np.ndarray) -> np.ndarray:
        return self.first[idx] % self.buffer.capacity

    # ---------------------------------------------------------------------------------- sampling
    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """Indices (into this store) of ``n`` intact episodes drawn uniformly with replacement."""
        lo = self.intact_start()
        if lo >= len(self):
            raise ValueError("no intact complete episode to sample")
        return rng.integers(lo, len(self), size=n)

    def step_rows(
        self, idx: np.ndarray, rng: np.random.Generator, subseq_len: int | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Buffer rows ``[E, L]`` and a validity mask ``[E, L]`` for the episodes ``idx``.

        ``subseq_len=None``: every step (padded to the longest episode). Otherwise K steps per
        episode drawn uniformly without replacement (all steps when the episode has at most K).
        """
        lengths = self.length[idx]
        starts = self.start_rows(idx)
        longest = int(lengths.max())
        if subseq_len is None or subseq_len >= longest:
            width = longest
            offsets = np.broadcast_to(np.arange(width), (len(idx), width))
        else:
            width = int(subseq_len)
            keys = rng.random((len(idx), longest))
            keys[np.arange(longest)[None, :] >= lengths[:, None]] = np.inf
            offsets = np.argpartition(keys, width - 1, axis=1)[:, :width]
        # Padded positions (past an episode's end) got key inf, so they are chosen only when the
        # episode has fewer than K steps; either way an offset is valid iff it is a real step.
        mask = offsets < lengths[:, None]
        offsets = np.where(mask, offsets, 0)
        rows = (starts[:, None] + offsets) % self.buffer.capacity
        return rows.astype(np.int64), mask

    # -------------------------------------------------------------------------------- checkpoint
    def state_dict(self) -> dict[str, Any]:
        return {"first": self.first.copy(), "length": self.length.copy(), "returns": self.returns.copy(),
                "rejected": self.rejected}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.first = np.asarray(state["first"], dtype=np.int64).copy()
        self.length = np.asarray(state["length"], dtype=np.int64).copy()
        self.returns = np.asarray(state["returns"], dtype=np.float64).copy()
        self.rejected = int(state.get("rejected", 0))
