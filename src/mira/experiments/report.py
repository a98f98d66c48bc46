"""Tables and figures of a set of runs, in the layout of the paper's Tables 2/3 and Figures 3–5.

``write_report(paths, out_dir)`` takes run directories and/or directories containing runs (a sweep's
``OUT``), and writes into ``out_dir``:

- ``report.md`` — every table and figure with the metric definitions and notes, every intervention, and
  every structural diagnosis (including those of an ablation that cannot act on them);
- ``table_<algo>.md`` / ``table_<algo>.csv`` — method rows; per task the asymptotic performance and
  the sample efficiency in units of 10^5 environment steps (mean ± std over seeds, "—" when no seed
  reached 50% of the Dense oracle; "(k/n)" when only k of n seeds did);
- ``metrics.csv`` — one row per (algo, task, method) with every number, IQM and its 95% CI;
- ``aggregate.csv`` — per (algo, method), the IQM of oracle-normalised asymptotic performance over
  all tasks and seeds with a stratified-bootstrap 95% CI (tasks are the strata);
- ``runs.csv`` — one row per run;
- ``curves_<algo>.png`` — Figures 3/4: mean ± 1 std over seeds, one panel per task, one line per
  method; ``ablation_<algo>.png`` — Figure 5 (MIRA vs. w/o MCM vs. w/o SRR) when they are present;
- ``runs/<task>_<algo>_<method>_seed<k>.png`` — per run, MCM's anomaly score with threshold,
  triggers and accepted/rejected SRR edits, and each factor's attention weight, when the run has
  ``diagnostics.csv`` or ``attn_*`` columns in ``train.csv``;
- ``interventions.csv`` — one row per intervention of any run: step, why, the edit installed (if
  any), and the evaluation return before and after it.

A run started from a program file (``mira train --program FILE``) is told apart from the runs of the
task's own program: its column and curve panel are the task and the file's stem ("HalfCheetah ·
wrong_gate"), with the steps where a run installed a new program marked; the normalised aggregate
counts the task's own program only.

Only complete runs (status finished at their step budget) enter tables and curves unless
``include_incomplete`` is set; the others are listed in the notes. Metric definitions are in
:mod:`mira.experiments.metrics`. Wall-time columns (``wall_s*``) are the only columns that differ
between two sweeps of the same grid.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mira.errors import UsageError
from mira.experiments import metrics as M
from mira.experiments.grid import order_methods, task_label
from mira.experiments.plots import Curve, plot_learning_curves, plot_run_diagnostics
from mira.experiments.runs import read_json
from mira.experiments.tables import (
    MIN_SEEDS_FOR_CI,
    SE_UNIT,
    csv_text,
    fmt_return,
    fmt_steps_1e5,
    md_table,
    spread_label,
    spread_text,
)
from mira.explain import interventions, structural_diagnosis
from mira.runio.atomic import atomic_write_text
from mira.runio.csvlog import read_csv

METHOD_TITLES = {
    "dense": "Dense R (oracle)", "sparse": "Sparse R", "hars": "HARS (inner loop only)", "mira": "MIRA",
    "mira-no-mcm": "MIRA w/o MCM",
    "mira-no-srr": "MIRA w/o SRR", "lare": "LaRe", "rd": "RD", "ircr": "IRCR", "vib": "VIB", "sb3": "SB3 SAC (dense R)",
}
TASK_ORDER = ("halfcheetah", "humanoidstandup", "humanoid")
ALGO_ORDER = ("ddpg", "sac")
ALGO_TABLE = {"ddpg": "Table 2", "sac": "Table 3"}
ABLATION = ("mira", "mira-no-mcm", "mira-no-srr")
ORACLE = "dense"
_SKIP_DIRS = {"tb", "checkpoints", "programs", "interventions", "llm", "_sweep", "__pycache__"}


@dataclass
class RunRecord:
    """What a report needs from one run directory."""

    path: Path
    task: str
    task_title: str
    method: str
    algo: str
    seed: int
    steps: int
    status: str
    final_step: int
    eval_steps: list[int]
    eval_returns: list[float]
    wall_s: float | None
    program: str = ""
    """The stem of the initial program file the run started from; "" for the task's own program."""

    @property
    def panel(self) -> str:
        return panel_key(self.task, self.program)

    @property
    def panel_title(self) -> str:
        return self.task_title + (f" · {self.program}" if self.program else "")

    @property
    def run_id(self) -> str:
        return f"{self.panel}/{self.algo}/{self.method}/seed{self.seed}"

    @property
    def complete(self) -> bool:
        return self.status == "finished" and self.final_step == self.steps and bool(self.eval_steps)


@dataclass
class CellStats:
    """One (algo, task, method) cell of a table, over seeds."""

    algo: str
    task: str
    method: str
    seeds: list[int]
    asymptotic: list[float]
    asym_mean: float
    asym_std: float
    iqm: float
    iqm_low: float
    iqm_high: float
    oracle: float | None
    threshold: float | None
    sample_eff: list[int | None]
    se_mean: float | None
    se_std: float | None
    reached: int
    wall_mean: float | None
    program: str = ""

    @property
    def panel(self) -> str:
        return panel_key(self.task, self.program)


def panel_key(task: str, program: str) -> str:
    """A table column and figure panel: the task, or the task started from a named initial program."""
    return f"{task}[{program}]" if program else task


@dataclass
class ReportResult:
    out_dir: Path
    files: list[Path] = field(default_factory=list)
    cells: list[CellStats] = field(default_factory=list)
    runs: list[RunRecord] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------- loading


def discover_runs(paths: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """Run directories (those holding ``config.json``) at or below each path, deduplicated: in the order
    the paths are given, each path's runs sorted, so that a run named earlier wins a duplicate."""
    found: list[Path] = []
    for p in paths:
        root = Path(p)
        if not root.exists():
            raise UsageError(f"{root} does not exist")
        if (root / "config.json").is_file():
            found.append(root.resolve())
            continue
        if not root.is_dir():
            raise UsageError(f"{root} is neither a run directory nor a directory of runs")
        for dirpath, dirnames, filenames in os.walk(root):
            if "config.json" in filenames:
                found.append(Path(dirpath).resolve())
                dirnames[:] = []
            else:
                dirnames[:] = sorted(d for d in dirnames if d not in _SKIP_DIRS)
    return list(dict.fromkeys(found))


def _task_title(cfg_task: str, card: Any) -> tuple[str, str]:
    """(key, title): a built-in task is keyed by its name and titled by its environment
    (HalfCheetah); a task-card file by its file stem, which is also its title."""
    name = task_label(str(cfg_task))
    if name != str(cfg_task):
        return name, name
    if isinstance(card, dict) and isinstance(card.get("env_id"), str):
        return name, card["env_id"].split("-v")[0]
    return name, name


def load_run(path: Path) -> RunRecord:
    """Read a run directory; raises ``UsageError`` if its config.json is unusable."""
    try:
        saved = json.loads((path / "config.json").read_text(encoding="utf-8"))
        cfg = saved["config"]
        task, title = _task_title(cfg["task"], saved.get("task_card"))
        method, algo, seed, steps = str(cfg["method"]), str(cfg["algo"]), int(cfg["seed"]), int(cfg["steps"])
        program = Path(str(cfg["program"])).stem if cfg.get("program") else ""
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise UsageError(f"{path}/config.json is unusable ({exc})") from None
    try:
        status = json.loads((path / "status.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        status = {}
    rows = read_csv(path / "eval.csv")
    steps_l: list[int] = []
    rets: list[float] = []
    wall: float | None = None
    for r in rows:
        try:
            s, ret = int(float(r["step"])), float(r["return_mean"])
        except (KeyError, ValueError):
            continue
        steps_l.append(s)
        rets.append(ret)
        with contextlib.suppress(ValueError):
            wall = float(r.get("wall_s") or "nan")
    final_step = int(status.get("step") or (steps_l[-1] if steps_l else 0)) if isinstance(status, dict) else 0
    return RunRecord(path, task, title, method, algo, seed, steps, str(status.get("status", "unknown")),
                     final_step, steps_l, rets, wall if wall is not None and math.isfinite(wall) else None,
                     program)


# ------------------------------------------------------------------------------------- computing


def _ordered(values: Iterable[str], preferred: Sequence[str]) -> list[str]:
    names = list(dict.fromkeys(values))
    return [v for v in preferred if v in names] + sorted(v for v in names if v not in preferred)


def compute_cells(runs: Sequence[RunRecord], *, reps: int = 20_000,
                  seed: int = 0) -> tuple[list[CellStats], list[str]]:
    """Per (algo, task, initial program, method): metrics over seeds, with the Dense oracle of the same
    task and algo (from the same initial program if it has one, else the task's own)."""
    notes: list[str] = []
    groups: dict[tuple[str, str, str, str], list[RunRecord]] = {}
    for r in runs:
        groups.setdefault((r.algo, r.task, r.program, r.method), []).append(r)
    asym: dict[tuple[str, str, str, str], list[float]] = {}
    for key, rs in groups.items():
        rs.sort(key=lambda r: r.seed)
        budgets = sorted({r.steps for r in rs})
        if len(budgets) > 1:
            notes.append(f"{'/'.join(key)}: runs with different step budgets {budgets} are pooled")
        asym[key] = [M.asymptotic_performance(r.eval_steps, r.eval_returns, r.steps) for r in rs]
    cells: list[CellStats] = []
    for key, rs in groups.items():
        algo, task, program, method = key
        values = asym[key]
        oracle_key = next((k for k in ((algo, task, program, ORACLE), (algo, task, "", ORACLE)) if k in asym), None)
        oracle = M.mean_std(asym[oracle_key])[0] if oracle_key else None
        threshold = M.oracle_threshold(oracle) if oracle is not None else None
        se = [M.sample_efficiency(r.eval_steps, r.eval_returns, threshold) if threshold is not None else None
              for r in rs]
        se_mean, se_std, reached, _ = M.sample_efficiency_over_seeds(se)
        mean, std = M.mean_std(values)
        point, low, high = M.stratified_bootstrap_ci([values], reps=reps, seed=seed)
        walls = [r.wall_s for r in rs if r.wall_s is not None]
        cells.append(CellStats(algo, task, method, [r.seed for r in rs], values, mean, std, point, low, high,
                               oracle, threshold, se, se_mean, se_std, reached,
                               sum(walls) / len(walls) if walls else None, program))
    for algo, task in sorted({(a, t) for a, t, _, _ in groups}):
        if not any(k[:2] == (algo, task) and k[3] == ORACLE for k in groups):
            notes.append(f"{algo.upper()} {task}: no Dense oracle runs, so sample efficiency is n/a")
    return cells, notes


def aggregate(cells: Sequence[CellStats], *, reps: int = 20_000,
              seed: int = 0) -> tuple[list[dict[str, Any]], list[str]]:
    """Per (algo, method): IQM of oracle-normalised asymptotic performance (score / A_oracle) over all
    tasks and seeds, with a stratified-bootstrap CI (strata = tasks). Tasks whose oracle is missing
    or not positive are left out (a ratio to it would not be a score)."""
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    by_algo: dict[str, list[CellStats]] = {}
    if any(c.program for c in cells):
        notes.append("runs started from a program file are left out of the normalised aggregate (it counts "
                     "each task's own program)")
    for c in cells:
        if not c.program:
            by_algo.setdefault(c.algo, []).append(c)
    for algo in _ordered(by_algo, ALGO_ORDER):
        skipped = sorted({c.task for c in by_algo[algo] if c.oracle is None or c.oracle <= 0})
        if skipped:
            notes.append(f"{algo.upper()}: tasks left out of the normalised aggregate (oracle missing or "
                         f"≤ 0): {', '.join(skipped)}")
        methods = order_methods(c.method for c in by_algo[algo])
        for method in methods:
            strata = {c.task: [v / c.oracle for v in c.asymptotic] for c in by_algo[algo]
                      if c.method == method and c.oracle is not None and c.oracle > 0}
            if not strata:
                continue
            point, low, high = M.stratified_bootstrap_ci(strata, reps=reps, seed=seed)
            pooled = [v for vs in strata.values() for v in vs]
            rows.append({"algo": algo, "method": method, "tasks": ";".join(sorted(strata)),
                         "runs": len(pooled), "normalized_iqm": point, "ci_low": low, "ci_high": high,
                         "min_seeds": min(len(v) for v in strata.values()),
                         "normalized_mean": float(sum(pooled) / len(pooled)),
                         "normalized_min": min(pooled), "normalized_max": max(pooled)})
    return rows, notes


# ------------------------------------------------------------------------------------ formatting


def _spread_cell(c: CellStats) -> str:
    return spread_text(c.asymptotic, c.iqm, c.iqm_low, c.iqm_high)


def _asym_cell(c: CellStats) -> str:
    if len(c.seeds) == 1:  # one seed has no spread: "± 0" would claim one
        return fmt_return(c.asym_mean)
    return f"{fmt_return(c.asym_mean)} ± {fmt_return(c.asym_std, c.asym_mean)}"


def _se_cell(c: CellStats) -> str:
    if c.threshold is None:
        return "n/a"
    if c.se_mean is None:
        return "—"
    n = len(c.sample_eff)
    if n == 1:
        return fmt_steps_1e5(c.se_mean)
    text = f"{fmt_steps_1e5(c.se_mean)} ± {fmt_steps_1e5(c.se_std, c.se_mean)}"
    return text if c.reached == n else f"{text} ({c.reached}/{n})"


# --------------------------------------------------------------------------------------- writing

RUN_PLOTS = ("all", "interventions", "none")  # which runs get a per-run figure: see write_report


def write_report(paths: Iterable[str | os.PathLike[str]], out_dir: str | os.PathLike[str], *,
                 include_incomplete: bool = False, bootstrap_reps: int = 20_000, seed: int = 0,
                 plots: bool = True, run_plots: str = "all") -> ReportResult:
    """Write the tables, CSVs and figures for every run found at or below ``paths`` into ``out_dir``;
    ``run_plots`` (:data:`RUN_PLOTS`) picks the runs that get a diagnostics PNG of their own (the bulk of a
    large report): all, those with a recorded intervention, or none."""
    if run_plots not in RUN_PLOTS:
        raise UsageError(f"run plots must be one of {', '.join(RUN_PLOTS)}, not {run_plots!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = ReportResult(out)
    run_dirs = discover_runs(paths)
    if not run_dirs:
        raise UsageError("no run directories (with config.json) found under " + ", ".join(str(p) for p in paths))
    result.runs = records = [load_run(p) for p in run_dirs]
    seen: dict[tuple[str, str, str, str, int], Path] = {}
    used: list[RunRecord] = []
    for r in records:
        key = (r.algo, r.task, r.program, r.method, r.seed)
        if key in seen:
            result.notes.append(f"{r.run_id}: duplicate of {seen[key]}; {r.path} is left out")
            continue
        if not r.eval_steps:
            result.notes.append(f"{r.run_id}: no evaluation yet ({r.status}); left out")
            continue
        if not r.complete and not include_incomplete:
            result.notes.append(f"{r.run_id}: {r.status} at step {r.final_step} of {r.steps}; left out (incomplete)")
            continue
        seen[key] = r.path
        used.append(r)
    cells, notes = compute_cells(used, reps=bootstrap_reps, seed=seed)
    result.cells = cells
    agg_rows, agg_notes = aggregate(cells, reps=bootstrap_reps, seed=seed)
    result.notes += notes + agg_notes

    def write(name: str, text: str) -> Path:
        path = out / name
        atomic_write_text(path, text)
        result.files.append(path)
        return path

    write("runs.csv", csv_text(
        ["algo", "task", "method", "seed", "steps", "status", "final_step", "used", "asymptotic",
         "sample_eff_steps", "wall_s", "program"],
        _run_rows(records, used, cells)))
    write("metrics.csv", csv_text(
        ["algo", "task", "method", "seeds", "asymptotic_mean", "asymptotic_std", "asymptotic_iqm",
         "asymptotic_iqm_ci_low", "asymptotic_iqm_ci_high", "oracle_asymptotic", "threshold",
         "sample_eff_steps_mean", "sample_eff_steps_std", "reached", "wall_s_mean", "program"],
        ([c.algo, c.task, c.method, len(c.seeds), c.asym_mean, c.asym_std, c.iqm, c.iqm_low, c.iqm_high,
          c.oracle, c.threshold, c.se_mean, c.se_std, c.reached, c.wall_mean, c.program]
         for c in _sorted_cells(cells))))
    agg_cols = ["algo", "method", "tasks", "runs", "normalized_iqm", "ci_low", "ci_high", "min_seeds",
                "normalized_mean", "normalized_min", "normalized_max"]
    write("aggregate.csv", csv_text(agg_cols, ([r[k] for k in agg_cols] for r in agg_rows)))

    stories = {id(r): interventions(r.path) for r in used}
    rows_iv = [[r.algo, r.task, r.program, r.method, r.seed, i.step, i.why, i.edit, int(i.accepted),
                i.return_before, i.return_after] for r in used for i in stories[id(r)]]
    write("interventions.csv", csv_text(["algo", "task", "program", "method", "seed", "step", "why", "edit",
                                          "accepted", "return_before", "return_after"], rows_iv))
    task_titles = {r.task: r.task_title for r in used}
    titles = {r.panel: r.panel_title for r in used}
    md: list[str] = ["# MIRA experiment report\n",
                     f"{len(used)} runs in the tables ({len(records)} found). Asymptotic performance: mean "
                     "evaluation return over the final 10% of training (eval rows with step > 0.9·N, at "
                     "least the last). Sample efficiency: first evaluation step whose return reaches 50% "
                     "of the Dense oracle's asymptotic performance for the same task and algo, in units of "
                     "10^5 environment steps (for a negative oracle A the bar is A − 0.5·|A|). Cells are "
                     "mean ± std over seeds; sample efficiency averages the seeds that reached the bar, "
                     "(k/n) when only k of n did; — when none did. Returns are the extrinsic episodic "
                     "return of the deterministic policy; shaping never enters them.\n"]
    for algo in _ordered({c.algo for c in cells}, ALGO_ORDER):
        acells = [c for c in cells if c.algo == algo]
        tasks = _panels(acells)
        methods = order_methods(c.method for c in acells)
        by = {(c.panel, c.method): c for c in acells}
        header = ["Method"]
        for t in tasks:
            header += [f"{titles.get(t, t)}: Asymptotic Perf.", f"{titles.get(t, t)}: Sample Eff. (×10^5)"]
        rows_md = []
        rows_csv = []
        for m in methods:
            row = [METHOD_TITLES.get(m, m)]
            crow: list[Any] = [m]
            for t in tasks:
                c = by.get((t, m))
                row += [_asym_cell(c), _se_cell(c)] if c else ["", ""]
                crow += ([c.asym_mean, c.asym_std, None if c.se_mean is None else c.se_mean / SE_UNIT,
                          None if c.se_std is None else c.se_std / SE_UNIT, c.reached, len(c.seeds)]
                         if c else [None] * 6)
            rows_md.append(row)
            rows_csv.append(crow)
        n_seeds = sorted({len(c.seeds) for c in acells})
        if n_seeds == [1]:
            spread = "one seed (no spread to show)"
        else:
            spread = "mean ± std over " + (f"{n_seeds[0]} seeds" if len(n_seeds) == 1
                                          else f"{n_seeds[0]}–{n_seeds[-1]} seeds")
        caption = f"{algo.upper()} — layout of the paper's {ALGO_TABLE.get(algo, 'Table 2')}; {spread}."
        table = md_table(header, rows_md)
        write(f"table_{algo}.md", f"{caption}\n\n{table}")
        csv_header = ["method"]
        for t in tasks:
            csv_header += [f"{t}:asymptotic_mean", f"{t}:asymptotic_std", f"{t}:sample_eff_1e5_mean",
                           f"{t}:sample_eff_1e5_std", f"{t}:reached", f"{t}:seeds"]
        write(f"table_{algo}.csv", csv_text(csv_header, rows_csv))
        md += [f"## {algo.upper()} ({ALGO_TABLE.get(algo, 'Table 2')} layout)\n", caption + "\n", table]
        iqm_rows = []
        for m in methods:
            row = [METHOD_TITLES.get(m, m)]
            for t in tasks:
                c = by.get((t, m))
                row.append(_spread_cell(c) if c else "")
            iqm_rows.append(row)
        md += [f"Asymptotic performance over seeds: {spread_label([len(c.seeds) for c in acells])}:\n",
               md_table(["Method", *(titles.get(t, t) for t in tasks)], iqm_rows)]
        program_of = {c.panel: (c.task, c.program) for c in acells}
        for task in sorted({c.task for c in acells if c.program}):
            # The same IQMs turned round: one row per initial program, the layout of a flawed-program study.
            own = [t for t in tasks if program_of[t][0] == task]
            cols = [m for m in methods if any((t, m) in by for t in own)]
            md += [f"{algo.upper()} on {task_titles.get(task, task)} by initial program "
                   f"({spread_label([len(c.seeds) for c in acells if c.task == task])}; seeds):\n",
                   md_table(["Initial program", *(METHOD_TITLES.get(m, m) for m in cols)],
                             [[program_of[t][1] or "the task's own", *(
                                 f"{_spread_cell(c)} ({len(c.seeds)})" if c else ""
                                 for c in (by.get((t, m)) for m in cols))] for t in own])]
        arows = [r for r in agg_rows if r["algo"] == algo]
        if arows:
            with_ci = [r for r in arows if r["min_seeds"] >= MIN_SEEDS_FOR_CI]
            few = [r for r in arows if r["min_seeds"] < MIN_SEEDS_FOR_CI]
            if with_ci:
                md += ["Oracle-normalised asymptotic performance, IQM over all tasks and seeds "
                       f"[95% stratified-bootstrap CI] (at least {MIN_SEEDS_FOR_CI} seeds per task):\n",
                       md_table(["Method", "IQM", "95% CI", "runs"],
                                 [[METHOD_TITLES.get(r["method"], r["method"]), f"{r['normalized_iqm']:.3f}",
                                   f"[{r['ci_low']:.3f}, {r['ci_high']:.3f}]", str(r["runs"])] for r in with_ci])]
            if few:
                md += ["Oracle-normalised asymptotic performance over all tasks and seeds, mean [min, max] "
                       f"(fewer than {MIN_SEEDS_FOR_CI} seeds on some task):\n",
                       md_table(["Method", "mean", "[min, max]", "runs"],
                                 [[METHOD_TITLES.get(r["method"], r["method"]), f"{r['normalized_mean']:.3f}",
                                   f"[{r['normalized_min']:.3f}, {r['normalized_max']:.3f}]", str(r["runs"])]
                                  for r in few])]
        if plots:
            panels = {t: {m: [Curve(r.eval_steps, r.eval_returns) for r in used
                              if (r.algo, r.panel, r.method) == (algo, t, m)] for m in methods} for t in tasks}
            marks = {t: [(i.step, r.method) for r in used if (r.algo, r.panel) == (algo, t)
                         for i in stories[id(r)] if i.accepted] for t in tasks}
            fig = out / f"curves_{algo}.png"
            plot_learning_curves(panels, fig,
                                 title=f"{algo.upper()}: evaluation return, "
                                       + ("one seed" if n_seeds == [1] else "mean ± 1 std over seeds"),
                                 panel_titles=titles, method_titles=METHOD_TITLES, methods=methods, marks=marks)
            result.files.append(fig)
            md.append(f"![{algo.upper()} learning curves]({fig.name})\n")
            abl_tasks = [t for t in tasks if "mira" in panels[t] and panels[t]["mira"]
                         and any(panels[t].get(m) for m in ABLATION[1:])]
            if abl_tasks:
                fig = out / f"ablation_{algo}.png"
                plot_learning_curves({t: {m: panels[t].get(m, []) for m in ABLATION} for t in abl_tasks}, fig,
                                     title=f"Ablation ({algo.upper()}): MIRA vs. w/o MCM vs. w/o SRR, "
                                           "mean ± 1 std", panel_titles=titles, method_titles=METHOD_TITLES,
                                     methods=ABLATION, marks=marks)
                result.files.append(fig)
                md += [f"### Ablation ({algo.upper()}, Figure 5 layout)\n", f"![ablation]({fig.name})\n"]
    if rows_iv:
        md += ["## Interventions\n",
               "Every intervention of the tabulated runs: why it happened, the edit installed (`+` a factor "
               "added, `~` one rewritten; `-` nothing installed), and the mean evaluation return over the "
               "three evaluation intervals before and after it.\n",
               md_table(["Run", "Step", "Why", "Edit", "Return before → after"],
                         [[r.run_id, str(i.step), i.why, i.edit,
                           f"{fmt_return(i.return_before)} → {fmt_return(i.return_after)}"]
                          for r in used for i in stories[id(r)]])]
    diagnosed = [(r, d) for r in used if (d := structural_diagnosis(r.path)) is not None]
    if diagnosed:
        # An ablation's diagnosis that no edit followed shows here and nowhere else in the report.
        md += ["## Structural diagnoses\n",
               "Runs whose returns called their program flawed (the structural check): from which step, on how "
               "many cycles, the task feature that would have explained the episodic returns, and the "
               "returns' out-of-sample R² without and with it. A `mira` run repairs at the first such step (see "
               "Interventions); `mira-no-srr` logs the diagnosis and installs nothing.\n",
               md_table(["Run", "First flagged at", "Cycles", "Feature", "R² of returns: program → with it"],
                         [[r.run_id, str(d.first_step), str(d.cycles), d.feature, f"{d.r2:.2f} → {d.r2_with:.2f}"]
                          for r, d in diagnosed])]
    if plots and run_plots != "none":
        diag = _run_diagnostic_plots(used, out, result, only_with_interventions=run_plots == "interventions")
        if diag:
            md += (["## MCM diagnostics and factor attention per run\n"]
                   + [f"- {rid}: ![{rid}]({p.relative_to(out)})" for rid, p in diag] + [""])
    if result.notes:
        md += ["## Notes\n"] + [f"- {n}" for n in result.notes] + [""]
    write("report.md", "\n".join(md) + "\n")
    return result


def _panels(items: Iterable[CellStats | RunRecord]) -> list[str]:
    """Panel keys in table order: tasks as ``TASK_ORDER`` has them, each task's own program first."""
    pairs = {(i.task, i.program) for i in items}
    tasks = _ordered((t for t, _ in pairs), TASK_ORDER)
    return [panel_key(t, p) for t, p in sorted(pairs, key=lambda tp: (tasks.index(tp[0]), tp[1] != "", tp[1]))]


def _sorted_cells(cells: Sequence[CellStats]) -> list[CellStats]:
    algos = _ordered({c.algo for c in cells}, ALGO_ORDER)
    panels = _panels(cells)
    methods = order_methods(c.method for c in cells)
    return sorted(cells, key=lambda c: (algos.index(c.algo), panels.index(c.panel), methods.index(c.method)))


def _run_rows(records: Sequence[RunRecord], used: Sequence[RunRecord],
              cells: Sequence[CellStats]) -> list[list[Any]]:
    by = {(c.algo, c.panel, c.method): c for c in cells}
    used_ids = {id(r) for r in used}
    rows = []
    algos = _ordered({r.algo for r in records}, ALGO_ORDER)
    panels = _panels(records)
    methods = order_methods(r.method for r in records)
    for r in sorted(records, key=lambda r: (algos.index(r.algo), panels.index(r.panel), methods.index(r.method),
                                            r.seed, str(r.path))):
        asym: float | None = None
        se: int | None = None
        c = by.get((r.algo, r.panel, r.method))
        if id(r) in used_ids and c is not None and r.seed in c.seeds:
            i = c.seeds.index(r.seed)
            asym, se = c.asymptotic[i], c.sample_eff[i]
        rows.append([r.algo, r.task, r.method, r.seed, r.steps, r.status, r.final_step,
                     int(id(r) in used_ids), asym, se, r.wall_s, r.program])
    return rows


def _run_diagnostic_plots(runs: Sequence[RunRecord], out: Path, result: ReportResult,
                          only_with_interventions: bool = False) -> list[tuple[str, Path]]:
    made: list[tuple[str, Path]] = []
    for r in runs:
        decision_files = sorted((r.path / "interventions").glob("*/decision.json"))
        if only_with_interventions and not decision_files:
            continue
        diagnostics = read_csv(r.path / "diagnostics.csv")
        train_rows = read_csv(r.path / "train.csv")
        per_factor = bool(train_rows) and any(k.startswith(("attn_", "share_")) for k in train_rows[0])
        if not diagnostics and not per_factor:
            continue
        decisions = []
        for d in decision_files:
            if (data := read_json(d)) is not None:
                if data.get("step") is None:  # the step the intervention was made at is in its evidence
                    data["step"] = (read_json(d.parent / "evidence.json") or {}).get("step")
                decisions.append(data)
        factors: set[str] = set()
        for prog in sorted((r.path / "programs").glob("v*.json")):
            try:
                data = json.loads(prog.read_text(encoding="utf-8"))
                factors.update(str(f["name"]) for f in data.get("factors", []) if isinstance(f, dict))
            except (OSError, ValueError, KeyError, TypeError, AttributeError):
                continue
        path = out / "runs" / f"{r.task}{f'-{r.program}' if r.program else ''}_{r.algo}_{r.method}_seed{r.seed}.png"
        title = f"{r.panel_title} · {r.algo.upper()} · {METHOD_TITLES.get(r.method, r.method)} · seed {r.seed}"
        if plot_run_diagnostics(path, title=title, diagnostics=diagnostics, train_rows=train_rows,
                                decisions=decisions, factors=sorted(factors) or None,
                                returns=Curve(r.eval_steps, r.eval_returns)):
            result.files.append(path)
            made.append((r.run_id, path))
    return made
