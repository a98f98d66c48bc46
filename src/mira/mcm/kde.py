"""Healthy-regime density model of section 4.3.2: a Gaussian KDE over a FIFO buffer of diagnostics.

``log p(d) = log( (1/|B|) sum_j exp(-||d - d_j||² / (2h²)) )`` — eq. (19) with the kernel's
normalisation constant dropped (it cancels in percentile thresholds and relative comparisons). The
sum is evaluated with log-sum-exp, so a vector far from every buffered one gives a large finite
score rather than ``-inf``.

Why a KDE over a buffer: "healthy" learning is multi-modal (exploration phase, fast-improvement
phase, plateau), which a single Gaussian would blur; a fixed-size buffer bounds the per-cycle cost
to ``O(N_B · D)`` and, with FIFO eviction, lets the model follow the agent's changing competence.

The bandwidth is initialised by the median heuristic (median pairwise distance in the buffer) and
then moved slowly toward the current median heuristic by an EMA, so the score scale does not jump
each time the buffer changes by one vector.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

BANDWIDTH_EMA = 0.05
"""Rate ``ρ`` of the bandwidth EMA ``h ← (1-ρ) h + ρ h_median``: a ~20-cycle time constant, so the score
scale does not jump each time the buffer changes by one vector."""
BANDWIDTH_FLOOR = 0.05
"""Lower bound on the bandwidth, in standardised units: a buffer of (nearly) identical vectors must not make
every other vector infinitely anomalous."""


def _logsumexp(a: FloatArray) -> float:
    m = float(np.max(a))
    return m + float(np.log(np.sum(np.exp(a - m))))


class HealthyModel:
    """Fixed-capacity FIFO buffer of healthy diagnostic vectors with a Gaussian-kernel density.

    Parameters
    ----------
    dim:
        Diagnostic dimension ``D``.
    capacity:
        ``N_B``; once full, inserting evicts the oldest vector.
    bandwidth_ema:
        Rate ``ρ`` of ``h ← (1 - ρ) h + ρ · h_median`` in :meth:`update_bandwidth`.
    bandwidth_floor:
        Lower bound on ``h``: a buffer of (nearly) identical vectors must not produce a zero
        bandwidth, which would make every other vector infinitely anomalous.
    """

    def __init__(
        self, dim: int, capacity: int = 128, bandwidth_ema: float = BANDWIDTH_EMA,
        bandwidth_floor: float = BANDWIDTH_FLOOR
    ) -> None:
        if dim < 1 or capacity < 1:
            raise ValueError("dim and capacity must be >= 1")
        self.dim = dim
        self.capacity = capacity
        self.bandwidth_ema = bandwidth_ema
        self.bandwidth_floor = bandwidth_floor
        self._buf: deque[FloatArray] = deque(maxlen=capacity)
        self._stack: FloatArray | None = None
        self.bandwidth: float | None = None

    # ---------------------------------------------------------------------------------- buffer
    def __len__(self) -> int:
        return len(self._buf)

    @property
    def points(self) -> FloatArray:
        """The buffered vectors as an ``[n, D]`` array, oldest first."""
        if self._stack is None:
            self._stack = np.stack(list(self._buf)) if self._buf else np.zeros((0, self.dim), dtype=np.float64)
        return self._stack

    def insert(self, d: ArrayLike) -> None:
        """Append ``d`` (evicting the oldest vector when full)."""
        v = np.asarray(d, dtype=np.float64).reshape(self.dim).copy()
        if not np.all(np.isfinite(v)):
            raise ValueError("cannot insert a non-finite diagnostic vector into the healthy buffer")
        self._buf.append(v)
        self._stack = None

    # ---------------------------------------------------------------------------------- bandwidth
    def median_heuristic(self) -> float:
        """Median-heuristic bandwidth ``h = med / sqrt(2 log(n + 1))`` (floored).

        ``med`` is the median pairwise Euclidean distance of the ``n`` buffered vectors. The
        ``sqrt(2 log(n+1))`` factor (the form popularised by SVGD) makes a buffered vector at the
        median distance get kernel weight ``exp(-med²/2h²) = 1/(n+1)``, so the density is shaped by
        near neighbours. The bare ``h = med`` is ~3 standard deviations in D = 5 and smooths the
        healthy cloud into one blob in which even a 4σ shift of one metric barely registers.
        With fewer than 2 points the fallback is 1.0, the scale of robustly standardised data.
        """
        x = self.points
        n = x.shape[0]
        if n < 2:
            return 1.0
        sq = np.sum(x * x, axis=1)
        d2 = np.maximum(sq[:, None] + sq[None, :] - 2.0 * (x @ x.T), 0.0)
        iu = np.triu_indices(n, k=1)
        med = float(np.sqrt(np.median(d2[iu])))
        return max(med / float(np.sqrt(2.0 * np.log(n + 1.0))), self.bandwidth_floor)

    def init_bandwidth(self) -> float:
        """Set ``h`` from the median heuristic (used once, when scoring first becomes possible)."""
        self.bandwidth = self.median_heuristic()
        return self.bandwidth

    def update_bandwidth(self) -> float:
        """Move ``h`` a step ``ρ`` toward the current median heuristic (initialising it if unset)."""
        target = self.median_heuristic()
        if self.bandwidth is None:
            self.bandwidth = target
        else:
            self.bandwidth = max(
                (1.0 - self.bandwidth_ema) * self.bandwidth + self.bandwidth_ema * target,
                self.bandwidth_floor,
            )
        return self.bandwidth

    def _h(self) -> float:
        if self.bandwidth is None:
            raise RuntimeError("bandwidth is not initialised; call init_bandwidth() first")
        if len(self._buf) == 0:
            raise RuntimeError("the healthy buffer is empty")
        return self.bandwidth

    # ---------------------------------------------------------------------------------- density
    def _log_kernels(self, d: FloatArray, h: float) -> tuple[FloatArray, FloatArray]:
        diff = self.points - d[None, :]
        return -np.sum(diff * diff, axis=1) / (2.0 * h * h), diff

    def log_density(self, d: ArrayLike) -> float:
        """``log p_healthy(d)`` of eq. (19) without the kernel normalisation constant."""
        h = self._h()
        logk, _ = self._log_kernels(np.asarray(d, dtype=np.float64).reshape(self.dim), h)
        return _logsumexp(logk) - float(np.log(logk.size))

    def score(self, d: ArrayLike) -> float:
        """Anomaly score ``S = -log p_healthy(d)``, eq. (20)."""
        return -self.log_density(d)

    def grad_log_density(self, d: ArrayLike) -> FloatArray:
        """Closed-form ``∇_d log p_healthy(d)``, eq. (22).

        ``sum_j w_j (d_j - d) / h²`` with softmax weights ``w_j ∝ K_h(d - d_j)``: the direction of
        steepest ascent toward the healthy manifold. Equivalently ``(m(d) - d) / h²`` where
        ``m(d)`` is the kernel-weighted mean of the buffer (the mean-shift vector).
        """
        h = self._h()
        logk, diff = self._log_kernels(np.asarray(d, dtype=np.float64).reshape(self.dim), h)
        w = np.exp(logk - np.max(logk))
        w /= np.sum(w)
        return np.asarray(w @ diff / (h * h), dtype=np.float64)

    # ---------------------------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        """Plain-Python state (exact float64 round trip, ``weights_only``-loadable)."""
        return {
            "dim": self.dim,
            "capacity": self.capacity,
            "bandwidth_ema": self.bandwidth_ema,
            "bandwidth_floor": self.bandwidth_floor,
            "buffer": [[float(x) for x in v] for v in self._buf],
            "bandwidth": self.bandwidth,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore exactly what :meth:`state_dict` produced."""
        self.dim = int(state["dim"])
        self.capacity = int(state["capacity"])
        self.bandwidth_ema = float(state["bandwidth_ema"])
        self.bandwidth_floor = float(state["bandwidth_floor"])
        self._buf = deque((np.asarray(v, dtype=np.float64) for v in state["buffer"]), maxlen=self.capacity)
        self._stack = None
        bw = state["bandwidth"]
        self.bandwidth = None if bw is None else float(bw)


def top_contributors(gradient: ArrayLike, m: int) -> list[int]:
    """Indices of the ``m`` components with the largest ``|gradient|``, largest first (ties by index).

    Ranking by ``|∇|`` is the same as ranking by ``|∇ ⊙ (m(d) - d)|``: since
    ``∇ = (m(d) - d) / h²``, that product is ``h² ∇²`` componentwise, a monotone function of ``|∇|``.
    So "largest pull toward health" and "largest deviation weighted by pull" agree.
    """
    g = np.abs(np.asarray(gradient, dtype=np.float64).ravel())
    order = sorted(range(g.size), key=lambda i: (-g[i], i))
    return order[: max(0, m)]
