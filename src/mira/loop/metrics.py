"""Per-update training figures summed between two ``train.csv`` rows.

Every update returns a dict of scalar tensors (the agent's losses plus the reward source's figures).
Summing them one by one costs a few tensor ops per figure and per step, which adds up to a visible
share of a fast step; here each update's figures become one stacked vector, checked for NaN/Inf and
added in three ops. The set of names may change during a run (a new factor program brings new
attention figures): sums kept so far are then folded into per-name totals and a new vector starts.
"""

from __future__ import annotations

import torch


class MetricSums:
    """Sums and counts of scalar training figures, keyed by name."""

    def __init__(self) -> None:
        self._keys: tuple[str, ...] = ()
        self._vector: torch.Tensor | None = None
        self._count = 0
        self._folded: dict[str, tuple[float, int]] = {}  # name -> (sum, count) from earlier key sets

    def add(self, metrics: dict[str, torch.Tensor]) -> bool:
        """Add one update's figures; False when any of them is NaN or infinite (nothing is added then)."""
        if not metrics:
            return True
        values = torch.stack([v.detach().reshape(()).float() for v in metrics.values()])
        if not bool(torch.isfinite(values).all()):
            return False
        keys = tuple(metrics)
        if keys != self._keys:
            self._fold()
            self._keys = keys
        if self._vector is None:
            self._vector = values.double()
        else:
            self._vector += values
        self._count += 1
        return True

    def _fold(self) -> None:
        if self._vector is not None:
            for k, v in zip(self._keys, self._vector.tolist(), strict=True):
                total, n = self._folded.get(k, (0.0, 0))
                self._folded[k] = (total + v, n + self._count)
        self._vector, self._count = None, 0

    def means(self) -> dict[str, float]:
        """Mean of each figure over the updates that reported it."""
        self._fold()
        return {k: total / n for k, (total, n) in self._folded.items() if n}

    def clear(self) -> None:
        self._keys, self._vector, self._count, self._folded = (), None, 0, {}

    @staticmethod
    def non_finite(metrics: dict[str, torch.Tensor]) -> list[str]:
        """Names of the figures in ``metrics`` that hold a NaN or an infinity."""
        return sorted(k for k, v in metrics.items() if not bool(torch.isfinite(v).all()))
