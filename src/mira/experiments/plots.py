"""Figures of a report, drawn with Matplotlib's Agg canvas (no pyplot, no display, no global backend
switch): learning curves in the style of the paper's Figures 3/4, the ablation of Figure 5, and
per-run MCM / attention diagnostics."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mira.experiments.metrics import mean_std

FIGSIZE = (10.0, 4.0)
DPI = 120
STYLE: Any = {"font.size": 11, "axes.titlesize": 12, "axes.labelsize": 11, "legend.fontsize": 10,
         "xtick.labelsize": 10, "ytick.labelsize": 10}

# One fixed colour per method across every figure of a report.
METHOD_COLOURS = {
    "dense": "#000000", "hars": "#17becf", "mira": "#d62728", "mira-no-mcm": "#ff9896", "mira-no-srr": "#9467bd",
    "lare": "#1f77b4", "rd": "#2ca02c", "ircr": "#ff7f0e", "vib": "#8c564b", "sparse": "#7f7f7f",
}
_SPARE = ["#bcbd22", "#e377c2", "#aec7e8", "#98df8a", "#c5b0d5"]


NON_FACTOR_ATTN = {"attn_entropy", "attn_mean", "attn_max", "attn_min"}


def method_colour(method: str, index: int = 0) -> str:
    return METHOD_COLOURS.get(method, _SPARE[index % len(_SPARE)])


@dataclass
class Curve:
    """One seed's evaluation curve."""

    steps: Sequence[float]
    returns: Sequence[float]


def _compact_returns(ax: Any) -> None:
    """Label a return axis in thousands ("140k") once its range reaches six digits, whose full labels
    would run past the figure's left margin (HumanoidStandup's returns are of order 10^5)."""
    from matplotlib.ticker import FuncFormatter

    def label(x: float, _pos: Any = None) -> str:
        big = max(abs(v) for v in ax.get_ylim()) >= 1e5
        return f"{x / 1e3:g}k" if big and x != 0 else f"{x:g}"

    ax.yaxis.set_major_formatter(FuncFormatter(label))


def steps_label(x: float, _pos: Any = None) -> str:
    """Axis label for an environment-step count: 0, 500, 30k, 1.5M."""
    if x == 0:
        return "0"
    ax = abs(x)
    if ax >= 1e6:
        return f"{x / 1e6:g}M"
    if ax >= 1e3:
        return f"{x / 1e3:g}k"
    return f"{x:g}"


def band(curves: Sequence[Curve]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Steps, mean, std and seed count at every evaluation step present in any seed's curve."""
    by_step: dict[float, list[float]] = {}
    for c in curves:
        for s, r in zip(c.steps, c.returns, strict=True):
            by_step.setdefault(float(s), []).append(float(r))
    steps = np.array(sorted(by_step))
    stats = [mean_std(by_step[s]) for s in steps]
    mean = np.array([m for m, _ in stats])
    std = np.array([d for _, d in stats])
    count = np.array([len(by_step[s]) for s in steps])
    return steps, mean, std, count


def _figure(width: float, height: float) -> tuple[Any, Any]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI)
    canvas = FigureCanvasAgg(fig)
    return fig, canvas


def _save(fig: Any, path: Path) -> None:
    import io

    from mira.runio.atomic import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    atomic_write_bytes(path, buf.getvalue())


def plot_learning_curves(
    panels: Mapping[str, Mapping[str, Sequence[Curve]]],
    path: Path,
    *,
    title: str,
    panel_titles: Mapping[str, str],
    method_titles: Mapping[str, str],
    methods: Sequence[str],
    marks: Mapping[str, Sequence[tuple[float, str]]] | None = None,
) -> None:
    """One panel per task (or task and initial program), one line per method (mean over seeds) with a
    ±1 std band; ``marks`` ((step, method) per panel) draws a dashed line in the method's colour at each
    step where a run of that panel installed a program. More than four panels wrap onto further rows."""
    import matplotlib
    from matplotlib.ticker import FuncFormatter

    tasks = list(panels)
    n = max(1, len(tasks))
    cols = min(n, 4)
    rows = -(-n // cols)
    with matplotlib.rc_context(STYLE):
        width = FIGSIZE[0] if cols <= 2 else 4.2 * cols + 1.8
        height = FIGSIZE[1] * (1 if rows == 1 else 0.85 * rows)
        fig, _ = _figure(width, height)
        axes = list(fig.subplots(rows, cols, squeeze=False).flat)
        for ax in axes[len(tasks):]:
            ax.set_visible(False)
        handles: dict[str, Any] = {}
        mark_line: Any = None
        for i, (ax, task) in enumerate(zip(axes, tasks, strict=False)):
            drawn: list[tuple[np.ndarray, np.ndarray]] = []
            for step, method in sorted(set((marks or {}).get(task, ()))):
                colour = method_colour(method, methods.index(method) if method in methods else 0)
                mark_line = ax.axvline(step, color=colour, lw=0.9, ls="--", alpha=0.7)
            for j, method in enumerate(methods):
                curves = panels[task].get(method)
                if not curves:
                    continue
                steps, mean, std, _ = band(curves)
                colour = method_colour(method, j)
                marker = "o" if len(steps) <= 25 else None
                # A method whose runs repeat an earlier one's (MIRA with no edit is HARS bit for bit) would
                # hide that curve: it is drawn dashed on top.
                same = any(np.array_equal(steps, s) and np.array_equal(mean, m) for s, m in drawn)
                drawn.append((steps, mean))
                (line,) = ax.plot(steps, mean, color=colour, lw=1.8, marker=marker, ms=3.5, ls="--" if same else "-",
                                  label=method_titles.get(method, method))
                ax.fill_between(steps, mean - std, mean + std, color=colour, alpha=0.15, lw=0)
                handles.setdefault(method, line)
            letter = chr(ord("a") + i) if i < 26 else str(i)
            ax.set_title(f"({letter}) {panel_titles.get(task, task)}")
            ax.set_xlabel("environment steps")
            if i % cols == 0:
                ax.set_ylabel("episodic return")
            ax.xaxis.set_major_formatter(FuncFormatter(steps_label))
            _compact_returns(ax)
            ax.grid(True, alpha=0.3)
        fig.suptitle(title)
        ordered = [m for m in methods if m in handles]
        lines = [handles[m] for m in ordered]
        labels = [method_titles.get(m, m) for m in ordered]
        if mark_line is not None:
            lines.append(mark_line)
            labels.append("program installed")
        right = 1.0 - 2.4 / width
        if rows == 1:
            fig.subplots_adjust(left=0.75 / width, right=right, bottom=0.15, top=0.83, wspace=0.28)
        else:
            fig.subplots_adjust(left=0.75 / width, right=right, bottom=0.6 / height, top=1 - 0.7 / height,
                                wspace=0.28, hspace=0.5)
        fig.legend(lines, labels,
                   loc="center left", bbox_to_anchor=(right + 0.01, 0.5), frameon=False)
        _save(fig, path)


def _float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def _factor_columns(train_rows: Sequence[Mapping[str, str]], prefix: str,
                    factors: Sequence[str] | None) -> list[str]:
    """``train.csv``'s per-factor columns with ``prefix``: those of ``factors`` when given, else every one
    but the summary columns."""
    cols = sorted({k for row in train_rows[:1] for k in row if k.startswith(prefix)})
    if factors:
        return [c for c in cols if c[len(prefix):] in set(factors)]
    return [c for c in cols if c not in NON_FACTOR_ATTN]


def plot_run_diagnostics(
    path: Path,
    *,
    title: str,
    diagnostics: Sequence[Mapping[str, str]],
    train_rows: Sequence[Mapping[str, str]],
    decisions: Sequence[Mapping[str, Any]],
    factors: Sequence[str] | None = None,
    returns: Curve | None = None,
) -> bool:
    """The run's evaluation return, MCM anomaly score with threshold and triggers, attention weight per
    factor, and each factor's share of the return decomposition's r̂; every SRR decision marked on each
    panel (an installed edit with the version it installed).

    The decomposition's shares are drawn beside the attention because they can disagree, and the head's
    r̂ is what the agent is trained on. Columns are ``attn_<factor>`` and ``share_<factor>`` in
    ``train.csv``; with ``factors`` (the names found in the run's factor programs) only those are drawn,
    otherwise every such column but summary ones such as ``attn_entropy``. A panel is left out when its
    data is missing; returns False (and writes nothing) when the MCM, attention and share panels all are.
    """
    import matplotlib
    from matplotlib.ticker import FuncFormatter

    header = set(diagnostics[0]) if diagnostics else set()
    score_key = next((k for k in ("score", "S", "anomaly_score") if k in header), None)
    attn_cols = _factor_columns(train_rows, "attn_", factors)
    share_cols = _factor_columns(train_rows, "share_", factors)
    share_cols = [c for c in share_cols if any(np.isfinite(_float(r.get(c))) for r in train_rows)]
    # One colour per factor across both panels.
    names = sorted({c.partition("_")[2] for c in [*attn_cols, *share_cols]})
    has_mcm = score_key is not None
    has_attn = bool(attn_cols)
    has_shares = bool(share_cols)
    if not has_mcm and not has_attn and not has_shares:
        return False
    has_returns = returns is not None and len(returns.steps) > 0
    n = int(has_mcm) + int(has_attn) + int(has_shares) + int(has_returns)
    accepted = [(int(d["step"]), d.get("version")) for d in decisions
                if d.get("accepted") and d.get("step") is not None]
    rejected = [int(d["step"]) for d in decisions if not d.get("accepted") and d.get("step") is not None]
    with matplotlib.rc_context(STYLE):
        fig, _ = _figure(FIGSIZE[0], 3.2 * n + 0.6)
        axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
        k = 0
        if has_returns:
            assert returns is not None
            ax = axes[k]
            k += 1
            ax.plot(returns.steps, returns.returns, color="#d62728", lw=1.6, marker="o", ms=3,
                    label="evaluation return")
            ax.set_ylabel("episodic return")
            _compact_returns(ax)
            ax.set_title("Evaluation return (deterministic policy)")
            ax.grid(True, alpha=0.3)
        if has_mcm:
            assert score_key is not None
            ax = axes[k]
            k += 1
            steps = np.array([_float(r.get("step")) for r in diagnostics])
            score = np.array([_float(r.get(score_key)) for r in diagnostics])
            thr = np.array([_float(r.get("threshold")) for r in diagnostics])
            trig = np.array([_float(r.get("trigger")) > 0 or str(r.get("trigger")).lower() == "true"
                             for r in diagnostics])
            warm = np.array([_float(r.get("warmup")) > 0 for r in diagnostics])
            if warm.any():
                ax.axvspan(0, float(np.nanmax(steps[warm])), color="#bbbbbb", alpha=0.3, lw=0,
                           label="warm-up (no score yet)")
            ax.plot(steps, score, color="#1f77b4", lw=1.6, marker="o", ms=3, label="anomaly score S")
            if np.isfinite(thr).any():
                ax.plot(steps, thr, color="#555555", lw=1.2, ls="--", label="threshold τ (q-th pct.)")
            if trig.any():
                ax.scatter(steps[trig], score[trig], marker="v", s=70, color="#d62728", zorder=3,
                           label="trigger")
            ax.set_ylabel("anomaly score")
            ax.set_title("MCM: anomaly score S = −log p_healthy(d)")
            ax.grid(True, alpha=0.3)
        cmap = matplotlib.colormaps["tab10"]
        steps = np.array([_float(r.get("step")) for r in train_rows])
        for cols, ylabel, panel_title in (
                (attn_cols, "attention weight", "HARS factor attention (mean weight per factor)"),
                (share_cols, "share of r̂", "HARS return decomposition: each factor's share of r̂ (the agent's reward)")):
            if not cols:
                continue
            ax = axes[k]
            k += 1
            for col in cols:
                name = col.partition("_")[2]
                values = np.array([_float(r.get(col)) for r in train_rows])
                ax.plot(steps, values, lw=1.5, color=cmap(names.index(name) % 10), label=name)
            ax.set_ylabel(ylabel)
            ax.set_title(panel_title)
            ax.grid(True, alpha=0.3)
        for ax in axes:
            first = ax is axes[0]
            for j, (s, version) in enumerate(accepted):
                ax.axvline(s, color="#2ca02c", lw=1.5, label="edit installed" if j == 0 and first else None)
                if first and version is not None:
                    ax.annotate(f"v{version}", (s, 1.0), xycoords=("data", "axes fraction"), xytext=(3, -12),
                                textcoords="offset points", color="#2ca02c", fontsize=9)
            for j, s in enumerate(rejected):
                ax.axvline(s, color="#999999", lw=1.2, ls=":",
                           label="edit rejected" if j == 0 and first else None)
            ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
        axes[-1].set_xlabel("environment steps")
        axes[-1].xaxis.set_major_formatter(FuncFormatter(steps_label))
        fig.suptitle(title)
        height = 3.2 * n + 0.6
        fig.subplots_adjust(left=0.08, right=0.76, top=1 - 0.75 / height, bottom=0.6 / height, hspace=0.35)
        _save(fig, path)
    return True
