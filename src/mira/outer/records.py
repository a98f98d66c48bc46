"""The outer loop's per-cycle records: ``diagnostics.csv`` (the monitor's reading of every cycle) and
``plateau.csv`` (the plateau detector's reports and each escape's probation).

Both are opened lazily at the first cycle and rewound to it, so a resumed run appends after the rows its
checkpoint covers and never repeats or loses one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mira.mcm.records import METRIC_NAMES, MCMResult, row_fields
from mira.runio.csvlog import CsvLog
from mira.shaping.attribution import ReturnAttribution

PLATEAU_FIELDS = ("step", "event", "version", "feature", "center", "halfwidth", "median", "before", "rise")
"""``plateau.csv``: each plateau found (the band and the held-out return's windowed medians), each escape's
end of probation (``escape_kept`` or ``escape_rolled_back``, with the median since it was installed) and
``too_late``: a plateau left unanswered because an escape's probation would outlast the run."""
DIAGNOSTIC_EXTRA = ("version", "returns_cv_r2", "unexplained_gain", "unexplained", "structural_flaw")
"""``diagnostics.csv``'s columns after the monitor's metrics: the program version and the structural check."""


class CycleRecords:
    """Appends one row per cycle to ``diagnostics.csv`` and one per plateau event to ``plateau.csv``."""

    def __init__(self) -> None:
        self._diagnostics: CsvLog | None = None
        self._plateau: CsvLog | None = None

    def diagnostics(self, run_path: Path, step: int, result: MCMResult, version: int,
                    attribution: ReturnAttribution | None, structural_flaw: bool) -> None:
        if self._diagnostics is None:
            fields = [*row_fields(METRIC_NAMES), *DIAGNOSTIC_EXTRA]
            self._diagnostics = CsvLog(run_path / "diagnostics.csv", fields)
            self._diagnostics.rewind(step - 1)
        best = None if attribution is None else attribution.best
        self._diagnostics.append({
            **result.as_row(), "version": version,
            "returns_cv_r2": "" if attribution is None else attribution.program_r2,
            "unexplained_gain": "" if best is None else best.gain,
            "unexplained": "" if best is None else (best.feature if best.form == "value" else f"-{best.feature}^2"),
            # Whether the structural check calls the program flawed this cycle: the record of a diagnosis that
            # an ablation without SRR makes but cannot act on.
            "structural_flaw": "" if attribution is None else int(structural_flaw),
        })

    def plateau(self, run_path: Path, step: int, event: str, version: int, **row: Any) -> None:
        """One line of ``plateau.csv``: a plateau found, an escape's probation ended, or a plateau too late."""
        if self._plateau is None:
            self._plateau = CsvLog(run_path / "plateau.csv", PLATEAU_FIELDS)
            self._plateau.rewind(step - 1)
        self._plateau.append({"step": step, "event": event, "version": version, **row})
