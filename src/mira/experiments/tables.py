"""How a report writes numbers and tables: returns and step counts with a precision that fits their
scale, and CSV and Markdown tables. Kept apart from :mod:`mira.experiments.report`, which decides what
goes into them.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Iterable, Sequence
from typing import Any

SE_UNIT = 1e5
"""Sample efficiency is reported in units of 10^5 environment steps (the paper's Tables 2/3)."""


def _return_decimals(ref: float) -> int:
    ax = abs(ref)
    return 0 if ax >= 1000 else 1 if ax >= 10 else 2


def fmt_return(x: float | None, ref: float | None = None) -> str:
    """A return for a table: 10,733 / 612.4 / −1.32, with the precision of ``ref`` (default ``x``)."""
    if x is None or not math.isfinite(x):
        return "—"
    decimals = _return_decimals(x if ref is None or not math.isfinite(ref) else ref)
    return f"{x:,.{decimals}f}".replace("-", "−")


def fmt_steps_1e5(x: float | None, ref: float | None = None) -> str:
    """Steps in units of 10^5 with two decimals, or two significant digits below 0.1 (of ``ref``)."""
    if x is None or not math.isfinite(x):
        return "—"
    r = abs((x if ref is None else ref) / SE_UNIT)
    decimals = 2 if r >= 0.1 or r == 0 else max(2, 1 - math.floor(math.log10(r)))
    return f"{x / SE_UNIT:.{decimals}f}"


def csv_text(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """CSV text with a header; floats at full precision, None as an empty cell."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    for row in rows:
        w.writerow(["" if v is None else (repr(float(v)) if isinstance(v, float) else v) for v in row])
    return buf.getvalue()


def md_table(header: Sequence[str], rows: Iterable[Sequence[str]]) -> str:
    """A Markdown table, its first column left-aligned and the others centred."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] + [":---:"] * (len(header) - 1)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


MIN_SEEDS_FOR_CI = 5
"""Below this many seeds a bootstrap over them only restates their minimum and maximum, and an IQM trims
nothing: such figures are the mean and [min, max], labelled as such."""

def spread_label(seed_counts: list[int]) -> str:
    """What :func:`spread_text` shows for cells of these many seeds, said once above a table."""
    if all(n < MIN_SEEDS_FOR_CI for n in seed_counts):
        return f"mean [min, max] over seeds (fewer than {MIN_SEEDS_FOR_CI} seeds: no interval)"
    return f"IQM [95% bootstrap CI] where a cell has at least {MIN_SEEDS_FOR_CI} seeds, else mean [min, max]"


def spread_text(values: list[float], iqm: float, low: float, high: float) -> str:
    """A figure over seeds: the IQM with its bootstrap interval from ``MIN_SEEDS_FOR_CI`` seeds, else the
    mean with the [min, max] of the seeds (marked "mean")."""
    if len(values) >= MIN_SEEDS_FOR_CI:
        return f"{fmt_return(iqm)} [{fmt_return(low, iqm)}, {fmt_return(high, iqm)}]"
    mean = sum(values) / len(values)
    return f"mean {fmt_return(mean)} [{fmt_return(min(values), mean)}, {fmt_return(max(values), mean)}]"
