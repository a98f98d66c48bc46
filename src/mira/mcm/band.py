"""Localising a stagnation band (section 5.3.2): where a feature of the evaluation states piles up.

When MCM flags stagnation on HumanoidStandup, SRR needs ``(z_stag, δ)``: the narrow band of torso
heights the trapped policy keeps returning to, so that the escape bonus
``σ(α[z - z_stag]) · (β v_z)`` acts there and nowhere else.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from mira.mcm.standardize import MAD_TO_STD


def stagnation_band(
    values: ArrayLike, coverage: float = 0.5, scale: float = 1.0, min_halfwidth: float = 1e-3
) -> tuple[float, float]:
    """``(center, halfwidth)`` of the densest band of ``values`` (e.g. recent torso heights).

    The band is the *shortest* interval holding a ``coverage`` fraction of the values (the
    "shorth"); its center is the median of the values inside it and its halfwidth is
    ``scale ·`` half its length, floored at ``min_halfwidth``.

    Why not simply median ± MAD: for unimodal, symmetric data the two agree (with coverage 0.5
    the shorth's half-length is the MAD), but a trapped policy's states are often bimodal — a
    dense crouch plus scattered falls — and then the median lands between the modes while the
    shorth stays on the dense one. For fewer than 3 finite values the band is
    ``(median, max(scale · 1.4826 · MAD, min_halfwidth))``.
    """
    x = np.asarray(values, dtype=np.float64).ravel()
    x = np.sort(x[np.isfinite(x)])
    if x.size == 0:
        raise ValueError("stagnation_band needs at least one finite value")
    if not 0.0 < coverage <= 1.0:
        raise ValueError(f"coverage must be in (0, 1], got {coverage}")
    n = x.size
    if n < 3:
        med = float(np.median(x))
        mad = float(np.median(np.abs(x - med)))
        return med, max(scale * MAD_TO_STD * mad, min_halfwidth)
    k = max(2, math.ceil(coverage * n))
    widths = x[k - 1 :] - x[: n - k + 1]
    i = int(np.argmin(widths))  # first shortest window: deterministic on ties
    inside = x[i : i + k]
    return float(np.median(inside)), max(scale * 0.5 * float(widths[i]), min_halfwidth)
