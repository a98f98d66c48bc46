"""The monitor's plateau detector: learning has stalled with the policy settled in a narrow band of states.

The anomaly score asks whether this cycle's diagnostics look unlike the run's healthy cycles; a run that
is stuck from early on has no healthy cycles to differ from, and a crouch that the program explains well
is not an anomaly of the reward (section 5.3.2's case study: HumanoidStandup's policy settles at one
torso height and stays). This detector reads what stagnation looks like directly:

* the held-out return has stopped rising: the median of the last ``WINDOW`` cycles is less than
  ``MIN_RISE`` (relative) above the median of the ``WINDOW`` cycles before, for ``PATIENCE`` cycles in a
  row, after ``WARMUP_CYCLES`` (the first cycles are noise around the untrained policy);
* and the returns show that it is flat, not only that two medians happen to be level: the least-squares
  trend over those ``2 * WINDOW`` cycles, ``TREND_Z`` standard errors either side, lies within
  ``MIN_RISE`` per window of zero. On a noisy climb (Humanoid, whose held-out return moves 15-20% from
  one cycle to the next) two level medians are common and say nothing, and a sudden drop is not a
  plateau; on a run that sits (HumanoidStandup's crouch, about 1% noise) the interval is narrow
  (``bench/plateau_replay.py`` replays the detector on archived returns; the results page has the figures);
* the evaluation episodes settle in a narrow band of the card's ``band_feature``: the band holding half
  of the late-episode states (:func:`mira.mcm.band.stagnation_band`) is at most ``MAX_BAND_SHARE`` of the
  range the run has visited.

d_PEG (policy change per step) and d_RPE (the potential's residual) are recorded beside it as the
paper's signature (PEG collapsing, RPE stuck high), not required: their scale differs across tasks, and
the return's slope is what says a run is stuck. After a plateau is reported the detector forgets its
history, so the next report needs a fresh stall (two windows) of its own.

A flat stretch below the run's earlier best (a dip after the warm-up) is a plateau too; the detector
does not wait for a flat top. An escape installed in a dip is judged against a return that recovers
anyway, so its probation can keep an escape that did nothing: on HumanoidStandup, seed 0 kept one at
32k and was level with the same seed without escapes at 100k; its gain came from an escape at a flat
top (the results page). Whether to answer dips at all is open.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mira.mcm.band import stagnation_band

WINDOW = 10
"""Cycles per median: the return is compared as the median of the last WINDOW cycles against the median
of the WINDOW before (about 10 episodes each at the default cycle of one episode)."""
WARMUP_CYCLES = 30
"""Cycles before the first report: the early returns move with exploration and the first fits."""
MIN_RISE = 0.02
"""The relative rise of the windowed median below which the return counts as flat."""
PATIENCE = 2
"""Flat cycles in a row before a report: one flat comparison can be a dip."""
TREND_Z = 1.0
"""How sure the flatness must be: the trend's interval (this many standard errors) lies within ±MIN_RISE."""
MAX_BAND_SHARE = 0.1
"""How narrow the settled band must be: its half-width as a share of the visited range of the feature."""
LATE_SHARE = 0.5
"""Which states of an evaluation episode show where it settles: its last half."""


@dataclass
class Plateau:
    """A detected plateau: the flat return and the band where the episodes settle."""

    step: int
    recent_median: float
    previous_median: float
    rise: float
    feature: str
    center: float
    halfwidth: float
    visited: tuple[float, float]
    peg: float | None
    rpe: float | None
    start: float | None = None
    """The feature's median at the first step of the evaluation episodes: where the climb to the band began."""
    trend: float | None = None
    """The held-out return's least-squares trend over the compared cycles, relative, per ``WINDOW`` cycles."""
    trend_se: float | None = None
    """Its standard error, in the same unit."""

    def as_dict(self) -> dict[str, Any]:
        return {"step": self.step, "recent_median": self.recent_median, "previous_median": self.previous_median,
                "rise": self.rise, "feature": self.feature, "center": self.center, "halfwidth": self.halfwidth,
                "visited": list(self.visited), "start": self.start, "d_peg": self.peg, "d_rpe": self.rpe,
                "trend": self.trend, "trend_se": self.trend_se}


def late_states(values: np.ndarray, episode_index: np.ndarray, share: float = LATE_SHARE) -> np.ndarray:
    """The values of the last ``share`` of each episode's steps (where an episode settles)."""
    values, episode_index = np.asarray(values, dtype=np.float64), np.asarray(episode_index)
    keep = np.zeros(values.shape[0], dtype=bool)
    for e in np.unique(episode_index):
        where = np.flatnonzero(episode_index == e)
        keep[where[int(len(where) * (1.0 - share)):]] = True
    return values[keep]


def first_states(values: np.ndarray, episode_index: np.ndarray) -> np.ndarray:
    """The value at each episode's first step (where it starts, before the policy acts)."""
    values, episode_index = np.asarray(values, dtype=np.float64), np.asarray(episode_index)
    _, first = np.unique(episode_index, return_index=True)
    return values[first]


def relative_trend(returns: list[float] | np.ndarray) -> tuple[float, float]:
    """The least-squares slope of ``returns`` (one per cycle) and its standard error, both per ``WINDOW``
    cycles and relative to the median of the last ``WINDOW``. With two points there is no residual to
    estimate an error from: it is 0."""
    y = np.asarray(returns, dtype=np.float64)
    t = np.arange(y.size, dtype=np.float64) - (y.size - 1) / 2.0
    level = max(abs(float(np.median(y[-WINDOW:]))), 1e-8)
    slope = float(t @ (y - y.mean()) / (t @ t))
    residual = y - y.mean() - slope * t
    se = float(np.sqrt(residual @ residual / (y.size - 2) / (t @ t))) if y.size > 2 else 0.0
    return slope * WINDOW / level, se * WINDOW / level


class PlateauDetector:
    """Reports a :class:`Plateau` when the held-out return is flat and the episodes settle in a narrow band."""

    def __init__(self, feature: str) -> None:
        self.feature = feature
        self.returns: list[float] = []
        self.flat = 0
        self.cycles = 0

    def observe(self, step: int, held_out_return: float, settled: np.ndarray, visited: tuple[float, float],
                peg: float | None = None, rpe: float | None = None, start: float | None = None) -> Plateau | None:
        """One cycle: its mean held-out return, the band feature's values where the held-out episodes settle
        (:func:`late_states`), the range of the feature the run has visited, d_PEG/d_RPE for the record and
        the feature's value where the episodes start (:func:`first_states`)."""
        self.cycles += 1
        self.returns.append(float(held_out_return))
        self.returns = self.returns[-2 * WINDOW:]
        if self.cycles < WARMUP_CYCLES or len(self.returns) < 2 * WINDOW:
            return None
        previous = float(np.median(self.returns[:WINDOW]))
        recent = float(np.median(self.returns[WINDOW:]))
        rise = (recent - previous) / max(abs(previous), 1e-8)
        trend, se = relative_trend(self.returns)
        flat = rise < MIN_RISE and abs(trend) + TREND_Z * se < MIN_RISE
        self.flat = self.flat + 1 if flat else 0
        if self.flat < PATIENCE:
            return None
        center, half = stagnation_band(settled)
        span = max(float(visited[1] - visited[0]), 1e-8)
        if half > MAX_BAND_SHARE * span:
            return None
        self.reset()
        return Plateau(step, recent, previous, rise, self.feature, center, half,
                       (float(visited[0]), float(visited[1])), peg, rpe, start, trend, se)

    def reset(self) -> None:
        """Forget the history: the next report needs a stall of its own (after a report, an edit or a rollback)."""
        self.returns, self.flat = [], 0

    def state_dict(self) -> dict[str, Any]:
        return {"returns": list(self.returns), "flat": self.flat, "cycles": self.cycles}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.returns = [float(x) for x in state["returns"]]
        self.flat, self.cycles = int(state["flat"]), int(state["cycles"])
