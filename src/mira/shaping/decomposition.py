"""HARS's decomposition head: the per-step reward r̂ the potential is aligned to and the agent learns from.

The paper grounds MIRA in reward decomposability (section 3): G(τ) ≈ Σ_t Σ_i w_i f_i(s_t, a_t), with
the weights w found by "parametric alignment". This head makes that concrete over the current factor
program:

    r̂(s, a, s′) = Σ_{i ∈ PHI} w_i f_i(s′) + Σ_{j ∈ AUX} u_j f_j(s, a) + b,

fitted in closed form so that every stored episode's sum of r̂ matches its episodic return
(:class:`~mira.rewards.decomposition.EpisodeSumRegression`, ridge in standardised units), refitted
after every episode. PHI factors are read at s′ because a MuJoCo task's reward is earned *over* the
step (HalfCheetah's is the displacement during it, which the velocity at s′ tracks far better than the
velocity at s). The head only ever sees episodic returns; the dense reward is never read, and no loss
of the critic or of Φ trains it.

The w_i are the interpretable weights of section 3: a weight near zero says a factor does not help
explain the returns, a sign against the factor's declared polarity says the program has it backwards,
and the regression's R² and residual say how much of the return the program cannot express. They are
logged (``w_<factor>``, ``share_<factor>``, ``decomp_r2``) and handed to MCM/SRR as evidence.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from mira.rewards.decomposition import EpisodeSumRegression
from mira.rewards.episodes import EpisodeStore
from mira.shaping.columns import FactorColumns
from mira.shaping.factors import FactorSource

DECOMPOSE_RIDGE = 1.0
"""The largest ridge (in standardised units: one pseudo-episode) the leave-one-episode-out selection
may choose; it picks among ``DECOMPOSE_RIDGE · 10⁻ᵏ`` so the ridge fades as episodes pin the weights."""
DECOMPOSE_MIN_EPISODES = 2
"""Finished episodes needed before the head's first fit (r̂ is 0 until then): one return says nothing
about how the factors share it."""
DECOMPOSE_MAX_EPISODES = 5_000
"""Episodes whose summed features the head keeps (oldest dropped first): O(d) each, so many cost little."""


def log_fields(phi_names: list[str], aux_names: list[str]) -> tuple[str, ...]:
    """The ``train.csv`` columns of :meth:`DecompositionHead.figures` for a program's factors."""
    names = feature_names(phi_names, aux_names)
    return (*(f"w_{n}" for n in names), *(f"share_{n}" for n in names[:-1]), "decomp_r2", "decomp_loss")


def feature_names(phi_names: list[str], aux_names: list[str]) -> list[str]:
    """Names of the head's features in order: PHI factors (at s′), AUX factors, ``bias``."""
    return [*phi_names, *aux_names, "bias"]


class DecompositionHead:
    """r̂ as a linear function of one transition's factor values, fitted to episodic returns.

    The head reads factor values from the columns its owner keeps (``features(phi_next, aux)``);
    the owner feeds it each finished episode, and a new program's head the episodes still stored. The
    ridge is centred (each feature penalised by its spread across episodes, not its size) and chosen at
    each fit by leave-one-episode-out error: summed over an episode a program's factors are nearly
    collinear (effort, posture and the bias move with speed), and a fixed ridge would move weight along
    that direction (a control cost fitted as a bonus), while the selected one lets the returns decide.
    """

    def __init__(self, phi_names: list[str], aux_names: list[str]) -> None:
        self.phi_names, self.aux_names = list(phi_names), list(aux_names)
        self.names = feature_names(self.phi_names, self.aux_names)
        self.regression = EpisodeSumRegression(len(self.names), ridge=DECOMPOSE_RIDGE, centred=True, select=True,
                                               max_episodes=DECOMPOSE_MAX_EPISODES)
        self.weights = np.zeros(len(self.names), dtype=np.float64)
        """The current (w, u, b): zero until ``DECOMPOSE_MIN_EPISODES`` episodes have been fitted."""
        self.shares = np.zeros(len(self.names) - 1, dtype=np.float64)
        """Each factor's share of mean |r̂ − b| over the last fitted episode (sums to 1, bias excluded)."""

    @property
    def fitted(self) -> bool:
        return self.regression.fits > 0

    def features(self, phi_next: np.ndarray, aux: np.ndarray) -> np.ndarray:
        """The head's inputs ``[N, D]`` from PHI values at s′ and AUX values at (s, a) (float64)."""
        n = phi_next.shape[0]
        return np.concatenate([phi_next.astype(np.float64), aux.astype(np.float64), np.ones((n, 1))], axis=1)

    def add_episode(self, x: np.ndarray, episode_return: float) -> None:
        """An episode's per-step features ``[T, D]`` and its return; refits once enough are stored."""
        self.regression.add(x.sum(axis=0), episode_return, float(x.shape[0]))
        if self.regression.count >= DECOMPOSE_MIN_EPISODES:
            self.weights = self.regression.fit().copy()
            contrib = np.abs(x[:, :-1] * self.weights[None, :-1]).mean(axis=0)
            total = float(contrib.sum())
            self.shares = contrib / total if total > 0 else np.zeros_like(contrib)

    def figures(self) -> dict[str, float]:
        """What is logged per update: each weight, each factor's share, the fit's R² (0 when the returns
        have no variance) and loss."""
        out = {f"w_{n}": float(w) for n, w in zip(self.names, self.weights, strict=True)}
        out.update({f"share_{n}": float(s) for n, s in zip(self.names[:-1], self.shares, strict=True)})
        if self.fitted:  # before the first fit there is no R² nor residual to report
            out["decomp_r2"] = self.regression.r2 if np.isfinite(self.regression.r2) else 0.0
            out["decomp_loss"] = self.regression.loss
        return out

    def describe(self) -> dict[str, Any]:
        """The fitted decomposition as evidence: weights, shares, R², residual, episodes."""
        return {"features": list(self.names), "weights": dict(zip(self.names, map(float, self.weights), strict=True)),
                "shares": dict(zip(self.names[:-1], map(float, self.shares), strict=True)),
                "r2": self.regression.r2, "per_step_residual_rms": float(np.sqrt(self.regression.loss))
                if np.isfinite(self.regression.loss) else float("nan"),
                "episodes": self.regression.count, "phi_at": "next",
                "ridge": self.regression.chosen_ridge}

    def state_dict(self) -> dict[str, Any]:
        return {"names": list(self.names), "regression": self.regression.state_dict(),
                "weights": self.weights.copy(), "shares": self.shares.copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if list(state["names"]) != self.names:
            raise ValueError(f"checkpoint decomposition features {state['names']} do not match {self.names}")
        self.regression.load_state_dict(state["regression"])
        self.weights = np.asarray(state["weights"], dtype=np.float64).copy()
        self.shares = np.asarray(state["shares"], dtype=np.float64).copy()


class DecomposedReward:
    """r̂ over the current program: a :class:`DecompositionHead` fed from the factor columns, evaluated
    on stored rows (relabelling) and on raw transitions (held-out rollouts)."""

    def __init__(self, factors: FactorSource, columns: FactorColumns) -> None:
        self.factors, self.columns = factors, columns
        self.head = DecompositionHead(list(factors.phi_names), list(factors.aux_names))
        self.changed()

    def _inputs(self, rows: np.ndarray) -> np.ndarray:
        _, phi_next, aux = self.columns.numpy_rows(rows)
        return self.head.features(phi_next, aux)

    def add_episode(self, rows: np.ndarray, episode_return: float) -> None:
        """A finished episode's rows (factors evaluated or pending) and its return; refits the head."""
        self.head.add_episode(self._inputs(np.asarray(rows, dtype=np.int64)), float(episode_return))
        self.changed()

    def refit(self, episodes: EpisodeStore, capacity: int) -> None:
        """Fit the (fresh) head on every stored episode still intact: a new program's first fit."""
        episodes.prune()
        for i in range(episodes.intact_start(), len(episodes)):
            first, n = int(episodes.first[i]), int(episodes.length[i])
            rows = (first + np.arange(n)) % capacity
            self.head.add_episode(self._inputs(rows), float(episodes.returns[i]))
        self.changed()

    def changed(self) -> None:
        """Take the head's new weights: as tensors for relabelling, as figures for the log."""
        w = self.head.weights
        k, k_aux = len(self.head.phi_names), len(self.head.aux_names)
        t = torch.from_numpy(w.astype(np.float32))
        self._w_n, self._w_aux, self._w_bias = t[:k], t[k:k + k_aux], float(w[-1])
        self.metrics = {name: torch.tensor(v, dtype=torch.float32) for name, v in self.head.figures().items()}

    def of_rows(self, rows: torch.Tensor) -> torch.Tensor:
        """r̂ of stored rows ``[B]`` (their factors must be evaluated), on the CPU."""
        r = torch.full((rows.shape[0],), self._w_bias, dtype=torch.float32)
        if self._w_n.numel():
            r = r.addmv_(self.columns.phi_next.index_select(0, rows), self._w_n)
        if self._w_aux.numel():
            r = r.addmv_(self.columns.aux.index_select(0, rows), self._w_aux)
        return r

    def of_transitions(self, obs: np.ndarray, actions: np.ndarray, next_obs: np.ndarray) -> np.ndarray:
        """r̂ of raw transitions (float32 arrays ``[N, ·]``): ``[N]`` float64."""
        if obs.shape[0] == 0:
            return np.zeros(0)
        f = self.factors
        aux = f.aux(obs, np.asarray(actions, dtype=np.float32)) if f.aux_names else np.zeros((len(obs), 0))
        x = self.head.features(f.phi(next_obs), aux)
        return np.asarray(x @ self.head.weights, dtype=np.float64)
