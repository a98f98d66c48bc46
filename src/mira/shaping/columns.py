"""Each stored transition's factor values, kept beside the replay buffer, and the statistics HARS
normalises with.

HARS evaluates the program's factors once per stored transition — PHI at s and at s′, AUX at (s, a) —
into columns sized like the replay buffer, so shaping a sampled batch is a gather, not a call into the
(sandbox-checked, NumPy) factor code. Rows are evaluated lazily, in vectorised batches of the rows
stored since the last batch that needed one of them: one evaluation per step would run the factor code
and the statistics on one row at a time. Whoever reads a row first calls :meth:`FactorColumns.ensure`.

With SHAPE factors in the program, Ψ(s) and Ψ(s′) (their sum) are kept per row too (``psi``,
``psi_next``); without them there are no such columns and no extra work.

The running statistics of PHI values (reset with a new program) and of observations (kept across
programs) are folded in as rows are evaluated; HARS snapshots them when its weights change.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from mira.replay import ReplayBuffer
from mira.shaping.factors import FactorSource, RunningStats

RECOMPUTE_CHUNK = 65_536
"""Rows per vectorised pass when factors (or Φ) are evaluated over many stored rows at once (after a
program change, or on a batch of observations): large enough to amortise the calls, small enough to
bound the temporary arrays of a million-row buffer."""


class FactorColumns:
    """PHI at s, PHI at s′ and AUX factor values of every stored row (``phi``, ``phi_next``, ``aux``), and Ψ at
    s and s′ (``psi``, ``psi_next``) when the program has SHAPE factors."""

    def __init__(self, factors: FactorSource, buffer: ReplayBuffer, obs_stats: RunningStats) -> None:
        self.factors = factors
        self.buffer = buffer
        self.obs_stats = obs_stats
        cap = buffer.capacity
        k, k_aux = len(factors.phi_names), len(factors.aux_names)
        self.phi = torch.zeros((cap, k), dtype=torch.float32)
        self.phi_next = torch.zeros((cap, k), dtype=torch.float32)
        self.aux = torch.zeros((cap, k_aux), dtype=torch.float32)
        self._np_phi, self._np_phi_next, self._np_aux = self.phi.numpy(), self.phi_next.numpy(), self.aux.numpy()
        self.shaping = bool(getattr(factors, "shape_names", None))
        """Whether the program has SHAPE factors (then ``psi``/``psi_next`` hold Ψ; else they are empty)."""
        n_psi = cap if self.shaping else 0
        self.psi = torch.zeros(n_psi, dtype=torch.float32)
        self.psi_next = torch.zeros(n_psi, dtype=torch.float32)
        self.factor_stats = RunningStats(k)
        self.pending: list[int] = []  # rows stored but not yet evaluated
        self._is_pending = np.zeros(cap, dtype=bool)
        self._flush_at = max(1, min(1024, cap // 2))

    def add(self, row: int) -> None:
        """A transition was stored at ``row``: evaluate it with the next batch of rows."""
        self.pending.append(row)
        self._is_pending[row] = True
        if len(self.pending) >= self._flush_at:
            self.flush()

    def ensure(self, rows: np.ndarray) -> None:
        """Evaluate the pending rows now if any of ``rows`` is among them."""
        if self.pending and self._is_pending[rows].any():
            self.flush()

    def flush(self) -> None:
        """Evaluate every pending row into the columns and fold them into the statistics."""
        if not self.pending:
            return
        rows = np.asarray(self.pending, dtype=np.int64)
        self.pending = []
        self._is_pending[rows] = False
        buf = self.buffer
        obs = buf.obs.numpy()[rows]
        phi_s = self.factors.phi(obs)
        self._np_phi[rows] = phi_s
        self._np_phi_next[rows] = self.factors.phi(buf.next_obs.numpy()[rows])
        if self.factors.aux_names:
            self._np_aux[rows] = self.factors.aux(obs, buf.action.numpy()[rows])
        if self.shaping:
            self._shape_rows(rows, obs, buf.next_obs.numpy()[rows])
        self.factor_stats.update(phi_s)
        self.obs_stats.update(obs)

    def recompute_all(self, chunk: int, reset_stats: bool = True) -> None:
        """Re-evaluate every stored row in vectorised chunks (after a program change); with
        ``reset_stats`` the PHI statistics restart from the stored states."""
        self.flush()  # pending rows' states still belong in the observation statistics
        buf = self.buffer
        n = buf.size
        chunk = max(1, chunk)
        stats = RunningStats(len(self.factors.phi_names))
        for start in range(0, n, chunk):
            stop = min(n, start + chunk)
            obs = buf.obs[start:stop].numpy()
            vals = self.factors.phi(obs)
            self._np_phi[start:stop] = vals
            self._np_phi_next[start:stop] = self.factors.phi(buf.next_obs[start:stop].numpy())
            if self.factors.aux_names:
                self._np_aux[start:stop] = self.factors.aux(obs, buf.action[start:stop].numpy())
            if self.shaping:
                self._shape_rows(np.arange(start, stop), obs, buf.next_obs[start:stop].numpy())
            stats.update(vals)
        if reset_stats:
            self.factor_stats = stats

    def _shape_rows(self, rows: np.ndarray, obs: np.ndarray, next_obs: np.ndarray) -> None:
        shape = self.factors.shape  # type: ignore[attr-defined]  # present where ``shaping`` is
        self.psi.numpy()[rows] = shape(obs)
        self.psi_next.numpy()[rows] = shape(next_obs)

    def numpy_rows(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(phi, phi_next, aux)`` of ``rows`` as NumPy arrays (evaluated first if pending)."""
        self.ensure(rows)
        return self._np_phi[rows], self._np_phi_next[rows], self._np_aux[rows]

    def state_dict(self) -> dict[str, Any]:
        """The evaluated rows (pending ones are evaluated first, so a resumed run flushes at the same points)."""
        self.flush()
        n = self.buffer.size
        out = {"phi": self.phi[:n].clone(), "phi_next": self.phi_next[:n].clone(), "aux": self.aux[:n].clone()}
        if self.shaping:
            out.update(psi=self.psi[:n].clone(), psi_next=self.psi_next[:n].clone())
        return out

    def load_state_dict(self, state: dict[str, Any]) -> None:
        n = state["phi"].shape[0]
        self.phi[:n] = state["phi"]
        self.phi_next[:n] = state["phi_next"]
        self.aux[:n] = state["aux"]
        if self.shaping:
            self.psi[:n] = state["psi"]
            self.psi_next[:n] = state["psi_next"]


def window_rows(buffer: ReplayBuffer, rows: np.ndarray, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Buffer rows of the ``w − 1`` steps before each of ``rows`` (oldest first), and whether each is in
    the same episode (the TCE's context windows)."""
    r = torch.from_numpy(rows)
    offs = torch.arange(w - 1, 0, -1)
    past = (r[:, None] - offs[None, :]) % buffer.capacity
    same_episode = buffer.episode_id[past] == buffer.episode_id[r][:, None]
    valid = (buffer.episode_step[r][:, None] >= offs[None, :]) & same_episode
    return past, valid

