"""The trainer's per-update figures: sums, means, NaN/Inf detection and a changing set of names."""

from __future__ import annotations

import math

import pytest
import torch

from mira.loop.metrics import MetricSums


def _m(**values: float) -> dict[str, torch.Tensor]:
    return {k: torch.tensor(v) for k, v in values.items()}


def test_means_over_updates_and_clear() -> None:
    sums = MetricSums()
    assert sums.add(_m(loss=1.0, q=10.0)) and sums.add(_m(loss=3.0, q=20.0))
    assert sums.means() == pytest.approx({"loss": 2.0, "q": 15.0})
    sums.clear()
    assert sums.means() == {}
    assert sums.add({}) and sums.means() == {}


def test_a_non_finite_figure_is_reported_and_not_added() -> None:
    sums = MetricSums()
    sums.add(_m(loss=1.0, q=2.0))
    bad = _m(loss=math.nan, q=math.inf)
    assert not sums.add(bad)
    assert MetricSums.non_finite(bad) == ["loss", "q"]
    assert MetricSums.non_finite(_m(loss=1.0)) == []
    assert sums.means() == pytest.approx({"loss": 1.0, "q": 2.0})


def test_names_that_come_and_go_are_averaged_over_the_updates_that_reported_them() -> None:
    sums = MetricSums()
    sums.add(_m(loss=1.0, attn_a=0.2))
    sums.add(_m(loss=3.0, attn_a=0.4))
    sums.add(_m(loss=5.0, attn_b=0.9))  # a new program: new attention names
    sums.add(_m(loss=1.0, attn_a=0.6))  # and back
    assert sums.means() == pytest.approx({"loss": 2.5, "attn_a": 0.4, "attn_b": 0.9})
