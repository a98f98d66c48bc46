"""What HARS keeps of the stored transitions, and what it derives from them between training steps.

* the current program's factor values of every stored row (:class:`~mira.shaping.columns.FactorColumns`)
  and the running statistics of factors and observations Φ normalises its inputs with;
* the stored episodes and σ_R, the running scale of episodic returns that Φ is learned in;
* the decomposition r̂ fitted to those episodes (:class:`~mira.shaping.decomposition.DecomposedReward`).

A new program (:meth:`FactorMemory.install`) re-evaluates every stored row and refits r̂ on the stored
episodes; the observation statistics, the episodes and σ_R carry over, as they do not depend on it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from mira.replay import ReplayBuffer
from mira.rewards.episodes import EpisodeStore
from mira.shaping.columns import RECOMPUTE_CHUNK, FactorColumns
from mira.shaping.decomposition import DECOMPOSE_MAX_EPISODES, DecomposedReward, DecompositionHead
from mira.shaping.factors import FactorSource, RunningStats
from mira.shaping.potential import STD_FLOOR, InputSnapshot

RETURN_SCALE_EMA = 0.05
"""Rate of the exponential average of squared episodic returns behind σ_R: about the last twenty
episodes, so the unit follows the policy's progress without jumping with one episode."""


class FactorMemory:
    """Factor columns, statistics, stored episodes, σ_R and r̂ over one replay buffer."""

    def __init__(self, buffer: ReplayBuffer, obs_dim: int) -> None:
        self.buffer = buffer
        self.obs_stats = RunningStats(obs_dim)
        self.episodes = EpisodeStore(buffer, DECOMPOSE_MAX_EPISODES)
        self.return_sq: float | None = None
        """EMA of squared episodic returns: σ_R² (see :attr:`phi_scale`)."""
        self.columns: FactorColumns  # these two come with the program (``install``)
        self.decomposed: DecomposedReward

    def install(self, factors: FactorSource, recompute: bool = False) -> None:
        """Columns and a fresh r̂ for ``factors``; with ``recompute`` (a program change after training
        began) every stored row is evaluated now, the factor statistics restart from the stored states,
        and r̂ is fitted on the stored episodes."""
        if recompute:
            self.columns.flush()  # with the old program: its rows' states stay in the observation statistics
        self.columns = FactorColumns(factors, self.buffer, self.obs_stats)
        self.decomposed = DecomposedReward(factors, self.columns)
        if recompute:
            self.columns.recompute_all(RECOMPUTE_CHUNK, reset_stats=True)
            self.decomposed.refit(self.episodes, self.buffer.capacity)

    @property
    def factor_stats(self) -> RunningStats:
        """Running statistics of the current program's PHI values."""
        return self.columns.factor_stats

    @property
    def phi_scale(self) -> float:
        """σ_R: the unit Φ is learned in, the root mean square of recent episodic returns (at least 1; 1
        until an episode has ended). Adam moves weights by about the learning rate per step whatever the
        gradient's size, so a potential in raw units that must reach returns of 10⁴–10⁵
        (HumanoidStandup) would need millions of updates; in units of σ_R it stays of order one on every
        task, and the alignment and joint losses are measured in those units."""
        if self.return_sq is None:
            return 1.0
        return max(1.0, math.sqrt(self.return_sq))

    def input_snapshot(self) -> InputSnapshot:
        """The statistics Φ normalises its inputs with, and σ_R, as of now (pending rows evaluated first)."""
        self.columns.flush()
        fs, os_ = self.factor_stats, self.obs_stats
        return InputSnapshot(fs.mean.copy(), np.maximum(fs.std, STD_FLOOR), os_.mean.copy(),
                             np.maximum(os_.std, STD_FLOOR), self.phi_scale)

    def on_episode_end(self, rows: np.ndarray, episode_return: float) -> bool:
        """Fold a finished episode into σ_R and, when it is stored whole, into r̂; True when r̂ changed."""
        if not math.isfinite(episode_return):
            return False
        sq = float(episode_return) ** 2
        rho = RETURN_SCALE_EMA
        self.return_sq = sq if self.return_sq is None else (1.0 - rho) * self.return_sq + rho * sq
        if not self.episodes.add(rows, episode_return):
            return False
        self.decomposed.add_episode(rows, episode_return)
        return True

    # ------------------------------------------------------------ per-episode sums (repair evidence)
    def recent_episodes(self, limit: int) -> tuple[list[np.ndarray], np.ndarray]:
        """Buffer rows and returns of the latest ``limit`` stored episodes still intact, oldest first."""
        self.episodes.prune()
        start = max(self.episodes.intact_start(), len(self.episodes) - limit)
        cap = self.buffer.capacity
        rows = [(int(self.episodes.first[i]) + np.arange(int(self.episodes.length[i]))) % cap
                for i in range(start, len(self.episodes))]
        return rows, self.episodes.returns[start:].astype(np.float64)

    def head_sums(self, rows: list[np.ndarray], factors: FactorSource | None = None) -> np.ndarray:
        """Per-episode sums ``[E, D]`` of the decomposition head's features: the current program's (from
        the columns), or another program's (its factors evaluated on the stored transitions now)."""
        flat, starts = _concat(rows)
        if factors is None:
            _, phi_next, aux = self.columns.numpy_rows(flat)
            x = self.decomposed.head.features(phi_next, aux)
        else:
            buf = self.buffer
            obs, nxt = buf.obs.numpy()[flat], buf.next_obs.numpy()[flat]
            aux = factors.aux(obs, buf.action.numpy()[flat]) if factors.aux_names else np.zeros((len(flat), 0))
            head = DecompositionHead(list(factors.phi_names), list(factors.aux_names))
            x = head.features(factors.phi(nxt), aux)
        return np.add.reduceat(x, starts, axis=0)

    def feature_sums(self, rows: list[np.ndarray], feature_values: Callable[[np.ndarray], dict[str, np.ndarray]]
                     ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, tuple[float, float]]]:
        """Per-episode sums of every task feature at s′, as its value and as minus its square, and each
        feature's observed range (see :mod:`mira.shaping.attribution`)."""
        flat, starts = _concat(rows)
        values = feature_values(self.buffer.next_obs.numpy()[flat].astype(np.float64))
        sums: dict[str, dict[str, np.ndarray]] = {}
        ranges: dict[str, tuple[float, float]] = {}
        for name, v in values.items():
            v = np.asarray(v, dtype=np.float64).reshape(-1)
            if not np.all(np.isfinite(v)):
                continue
            sums[name] = {"value": np.add.reduceat(v, starts), "neg_square": np.add.reduceat(-v * v, starts)}
            ranges[name] = (float(v.min()), float(v.max()))
        return sums, ranges

    def state_dict(self) -> dict[str, Any]:
        # The columns first: that evaluates pending rows (flush points stay the same on resume).
        columns = self.columns.state_dict()
        return {"columns": columns, "episodes": self.episodes.state_dict(),
                "head": self.decomposed.head.state_dict(), "return_sq": self.return_sq,
                "factor_stats": self.factor_stats.state_dict(), "obs_stats": self.obs_stats.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.return_sq = state.get("return_sq")
        self.factor_stats.load_state_dict(state["factor_stats"])
        self.obs_stats.load_state_dict(state["obs_stats"])
        self.columns.load_state_dict(state["columns"])
        if "head" in state:  # format 1 (before the decomposition head): the head starts empty
            self.episodes.load_state_dict(state["episodes"])
            self.decomposed.head.load_state_dict(state["head"])
            self.decomposed.changed()


def _concat(rows: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Episodes' rows end to end, and where each episode starts in them (for ``np.add.reduceat``)."""
    lengths = np.array([len(r) for r in rows], dtype=np.int64)
    return np.concatenate(rows).astype(np.int64), np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
