"""Experiments: resumable sweeps (local pool or Ray), the paper's metrics, and reports.

- :mod:`mira.experiments.grid` — sweep grids, presets (``paper-small``, ``paper``) and sweep files;
- :mod:`mira.experiments.sweep` — run a grid as independent ``mira train`` subprocesses;
- :mod:`mira.experiments.metrics` — asymptotic performance, sample efficiency, IQM, bootstrap CIs;
- :mod:`mira.experiments.report` — Table 2/3-style tables and Figure 3–5-style plots;
- :mod:`mira.experiments.tables` — how numbers and tables are written (returns, step counts, CSV, Markdown);
- :mod:`mira.experiments.cli` — the ``mira sweep`` and ``mira report`` subcommands.
"""

from mira.experiments.grid import RunSpec, SweepGrid, build_grid, load_sweep_file, preset_grid
from mira.experiments.metrics import (
    asymptotic_performance,
    iqm,
    mean_std,
    oracle_threshold,
    sample_efficiency,
    stratified_bootstrap_ci,
)
from mira.experiments.report import write_report
from mira.experiments.runs import plan_run
from mira.experiments.sweep import SweepOptions, SweepResult, dry_run, run_sweep

__all__ = [
    "RunSpec",
    "SweepGrid",
    "SweepOptions",
    "SweepResult",
    "asymptotic_performance",
    "build_grid",
    "dry_run",
    "iqm",
    "load_sweep_file",
    "mean_std",
    "oracle_threshold",
    "plan_run",
    "preset_grid",
    "run_sweep",
    "sample_efficiency",
    "stratified_bootstrap_ci",
    "write_report",
]
