"""Robust per-component standardisation followed by EMA smoothing (section 4.3.1).

The raw diagnostics live on wildly different scales (d_PEG is an entropy change per environment
step, ~1e-5; d_PVC is a correlation in [-1, 1]; d_RPE is a ratio around 1), and their scales
drift as training progresses. The KDE in ``kde.py`` uses one isotropic bandwidth, so every
component must first be put on a comparable, outlier-robust scale:

``z = (x - median(window)) / max(1.4826 · MAD(window), floor)``, clipped to ``±z_clip``,

where ``window`` holds the last ``window`` values of that component *before* the current one (a
cycle is judged against its recent past, not against itself), and then
``s_k = β s_{k-1} + (1 - β) z_k`` (``s`` starts at the first ``z``).

1.4826 makes the MAD a consistent estimator of the standard deviation for Gaussian data. The floor
``floor_abs + floor_rel · |median|`` avoids division by zero for (near-)constant components, e.g.
d_FAP with a single factor or d_PEG under DDPG's fixed noise. Clipping bounds the influence of one
absurd value (say a TPD spike right after a factor-set edit) on the smoothed series.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

MAD_TO_STD = 1.4826

WINDOW = 50
"""Rolling window (cycles) of the median/MAD. 50 cycles (250k steps at ΔT=5k) is long enough that a persistent
regime shift stays visible for ~25 cycles before the median absorbs it, short enough to follow training phases."""
EMA_BETA = 0.3
"""EMA decay ``β``. 0.3 keeps the smoothing light: a step change reaches 91% of its height by its second cycle,
so ``N_consecutive = 2`` is met at once, while a one-cycle spike (clipped at ``Z_CLIP``) leaves only
``β(1-β)·Z_CLIP`` ≈ 0.84 (about one healthy standard deviation of the smoothed series) in the next cycle; in
synthetic 5-D streams this gives ~2 false triggers per 300 healthy cycles."""
MAD_FLOOR_ABS = 1e-8
"""Absolute floor of the robust scale ``1.4826·MAD`` (avoids division by zero)."""
MAD_FLOOR_REL = 1e-3
"""Relative floor ``· |median|``: changes below 0.1% of a metric's typical level are noise."""
Z_CLIP = 4.0
"""Clip of standardised values, bounding one absurd value's effect on the EMA and the KDE (a 4-robust-σ
deviation is already far outside the healthy cloud; beyond that only the persistence matters)."""


class RobustStandardizer:
    """Rolling-window median/MAD standardiser with EMA smoothing, one independent track per component.

    Parameters
    ----------
    dim:
        Number of components (the diagnostic dimension D).
    window:
        Rolling-window length (cycles) for the median and MAD.
    beta:
        EMA decay ``β`` in ``s_k = β s_{k-1} + (1 - β) z_k``; larger is smoother and slower.
    min_history:
        Fewer than this many past values gives ``z = 0`` (no evidence yet) instead of dividing
        by a MAD estimated from one or two points.
    floor_abs, floor_rel:
        The scale floor is ``floor_abs + floor_rel · |median|``.
    z_clip:
        Standardised values are clipped to ``[-z_clip, z_clip]`` before smoothing.

    Non-finite raw values are treated as missing: that component gets ``z = 0`` and its window is
    left untouched, so one NaN cannot poison the median for ``window`` cycles.
    """

    def __init__(
        self,
        dim: int,
        window: int = WINDOW,
        beta: float = EMA_BETA,
        min_history: int = 5,
        floor_abs: float = MAD_FLOOR_ABS,
        floor_rel: float = MAD_FLOOR_REL,
        z_clip: float = Z_CLIP,
    ) -> None:
        if dim < 1 or window < 1:
            raise ValueError("dim and window must be >= 1")
        if not 0.0 <= beta < 1.0:
            raise ValueError(f"beta must be in [0, 1), got {beta}")
        self.dim = dim
        self.window = window
        self.beta = beta
        self.min_history = min_history
        self.floor_abs = floor_abs
        self.floor_rel = floor_rel
        self.z_clip = z_clip
        self._hist: list[deque[float]] = [deque(maxlen=window) for _ in range(dim)]
        self._ema: NDArray[np.float64] | None = None

    def standardize(self, x: ArrayLike) -> NDArray[np.float64]:
        """Standardise ``x`` against the current windows without changing any state."""
        xa = np.asarray(x, dtype=np.float64).reshape(self.dim)
        z = np.zeros(self.dim)
        for i, h in enumerate(self._hist):
            if len(h) < self.min_history or not np.isfinite(xa[i]):
                continue
            vals = np.fromiter(h, dtype=np.float64, count=len(h))
            med = float(np.median(vals))
            mad = float(np.median(np.abs(vals - med)))
            scale = max(MAD_TO_STD * mad, self.floor_abs + self.floor_rel * abs(med))
            z[i] = (xa[i] - med) / scale
        return np.clip(z, -self.z_clip, self.z_clip)

    def update(self, x: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Standardise ``x``, push it into the windows and advance the EMA.

        Returns ``(standardised, smoothed)``; the smoothed vector is what enters the KDE.
        """
        xa = np.asarray(x, dtype=np.float64).reshape(self.dim)
        was_ready = self.ready
        z = self.standardize(xa)
        for i, h in enumerate(self._hist):
            if np.isfinite(xa[i]):
                h.append(float(xa[i]))
        # The EMA starts at the first informative vector: the zeros of the warm-up would bias it.
        if self._ema is None or not was_ready:
            self._ema = z.copy()
        else:
            self._ema = self.beta * self._ema + (1.0 - self.beta) * z
        return z, self._ema.copy()

    @property
    def ready(self) -> bool:
        """True once every component seen so far has ``min_history`` past values, so that the next
        :meth:`update` returns real standardised values rather than the zeros of "no evidence yet".
        (A component that has never been finite does not hold readiness back.)"""
        seen = [len(h) for h in self._hist if len(h)]
        return bool(seen) and min(seen) >= self.min_history

    @property
    def smoothed(self) -> NDArray[np.float64] | None:
        """Last smoothed vector, or ``None`` before the first update."""
        return None if self._ema is None else self._ema.copy()

    def state_dict(self) -> dict[str, Any]:
        """Plain-Python state (lists of floats), exact for float64 and loadable with ``weights_only``."""
        return {
            "dim": self.dim,
            "window": self.window,
            "beta": self.beta,
            "min_history": self.min_history,
            "floor_abs": self.floor_abs,
            "floor_rel": self.floor_rel,
            "z_clip": self.z_clip,
            "hist": [list(h) for h in self._hist],
            "ema": None if self._ema is None else [float(v) for v in self._ema],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore exactly what :meth:`state_dict` produced (configuration included)."""
        self.dim = int(state["dim"])
        self.window = int(state["window"])
        self.beta = float(state["beta"])
        self.min_history = int(state["min_history"])
        self.floor_abs = float(state["floor_abs"])
        self.floor_rel = float(state["floor_rel"])
        self.z_clip = float(state["z_clip"])
        hist = state["hist"]
        if len(hist) != self.dim:
            raise ValueError(f"standardizer state has {len(hist)} components, expected {self.dim}")
        self._hist = [deque((float(v) for v in h), maxlen=self.window) for h in hist]
        ema = state["ema"]
        self._ema = None if ema is None else np.asarray(ema, dtype=np.float64)
