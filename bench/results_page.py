"""The results page, ``docs/results.md``: one current table per question, made from the archived runs.

The page spec ``bench/results.toml`` names, for every table, the question it answers, the archived
run directories it reads (``bench/archive/...``, kept in git by ``bench/archive.py``), the step
budgets at which it reads them, the paper's figure beside each method and the command that made the
runs. Every figure on the page is computed here from the runs' own ``eval.csv``; the commit and CPU
of each row are read from the runs' ``config.json``, so a row cannot claim a commit its runs did not
record. Rebuild the page after archiving runs:

    python bench/results_page.py            # write docs/results.md and its figures (docs/results/)
    python bench/results_page.py --check    # exit 1 if docs/results.md is not what the archives give

Figures over seeds follow ``mira report``: below 5 seeds the mean and [min, max] of the seeds (no
interval: a bootstrap over 3 values only restates their extremes); from 5 seeds the IQM with a
95% stratified-bootstrap interval. Final return is the mean evaluation return over the final 10% of
the budget; sample efficiency is the first evaluation step at which a run reaches 50% of the
``dense`` oracle's final return at the same budget ("—" if it never does), averaged over the seeds
that reach it.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mira.experiments import metrics as M
from mira.experiments.grid import order_methods
from mira.experiments.plots import Curve, plot_learning_curves
from mira.experiments.report import METHOD_TITLES, RunRecord, discover_runs, load_run, read_json
from mira.experiments.tables import MIN_SEEDS_FOR_CI, fmt_return, md_table, spread_label, spread_text

ROOT = Path(__file__).resolve().parents[1]
SPEC = ROOT / "bench" / "results.toml"
PAGE = ROOT / "docs" / "results.md"
FIGURES = "results"  # docs/results/<table id>.png
# bench/throughput.py writes its measured table between these markers; the page keeps that block as it is.
SPEED_BEGIN, SPEED_END = "<!-- throughput:begin -->", "<!-- throughput:end -->"


@dataclass
class Table:
    """One question of the page and the runs that answer it."""

    id: str
    title: str
    question: str
    budgets: list[int]
    sources: list[dict[str, Any]]
    command: str
    paper_ref: str = ""
    paper: dict[str, Any] = field(default_factory=dict)
    text: str = ""
    methods: list[str] = field(default_factory=list)
    titles: dict[str, str] = field(default_factory=dict)
    posture: str = ""
    """A task feature whose mean over the final evaluation episodes each run's ``posture.json`` holds
    (``bench/posture.py --write``): a column of where the policies are at the end."""
    escapes: bool = False
    """A column of the monitor's escape edits per seed: how many it installed by the last budget and how
    many of those its probation kept (the interventions' ``evidence.json`` and ``probation.json``)."""


@dataclass
class Pairs:
    """A paired experiment: forks of the same checkpoints (``mira train --fork``), one arm per program installed
    at the fork (the control installs none), the same fork seeds in every arm, on one machine."""

    id: str
    title: str
    question: str
    source: str
    arms: list[tuple[str, str]]
    """(arm, title): the arm is the installed program's file stem without its ``_sN`` parent tag and the fork's
    ``--set`` settings, joined by "+" (``agent.target_entropy=0``); the arm "" is the control, which changes nothing."""
    command: str
    text: str = ""


class SpecError(ValueError):
    """The page spec is malformed; the message names the table and the key."""


def load_spec(path: Path) -> tuple[dict[str, Any], list[Table | Pairs]]:
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise SpecError(f"{path}: {exc}") from None
    tables = []
    for i, raw in enumerate(data.get("table", [])):
        where = f"{path}: table {raw.get('id', i)!r}"
        if raw.get("kind") == "pairs":
            tables.append(load_pairs(raw, where))
            continue
        for key in ("id", "title", "question", "budgets", "runs", "command"):
            if key not in raw:
                raise SpecError(f"{where}: missing key {key!r}")
        budgets = raw["budgets"]
        if not budgets or not all(isinstance(b, int) and b > 0 for b in budgets):
            raise SpecError(f"{where}: budgets must be positive integers, got {budgets!r}")
        sources = [{"path": s} if isinstance(s, str) else dict(s) for s in raw["runs"]]
        for s in sources:
            if "path" not in s or not (ROOT / s["path"]).exists():
                raise SpecError(f"{where}: runs entry {s!r} names no existing path")
        tables.append(Table(raw["id"], raw["title"], raw["question"].strip(), list(budgets), sources,
                            raw["command"].strip(), raw.get("paper_ref", ""), dict(raw.get("paper", {})),
                            raw.get("text", "").strip(), list(raw.get("methods", [])),
                            dict(raw.get("titles", {})), raw.get("posture", ""), bool(raw.get("escapes", False))))
    return {k: v for k, v in data.items() if k != "table"}, tables


def load_pairs(raw: dict[str, Any], where: str) -> Pairs:
    """A ``[[table]]`` with ``kind = "pairs"``: ``runs`` is one folder of forks, ``arms`` its [stem, title] pairs."""
    for key in ("id", "title", "question", "runs", "arms", "command"):
        if key not in raw:
            raise SpecError(f"{where}: missing key {key!r}")
    if not isinstance(raw["runs"], str) or not (ROOT / raw["runs"]).exists():
        raise SpecError(f"{where}: runs {raw['runs']!r} names no existing path")
    return Pairs(raw["id"], raw["title"], raw["question"].strip(), raw["runs"],
                 [(str(a), str(t)) for a, t in raw["arms"]], raw["command"].strip(), raw.get("text", "").strip())


# ---------------------------------------------------------------------------------------- reading
@dataclass
class Row:
    """The runs of one method (and initial program) in a table."""

    method: str
    program: str
    runs: list[RunRecord]
    commits: list[str]
    cpus: list[str]
    settings: list[str]


def collect(table: Table) -> tuple[list[Row], list[str]]:
    """The table's runs grouped by (method, program); a run named by an earlier source wins a duplicate."""
    notes: list[str] = []
    seen: dict[tuple[str, str, int], Path] = {}
    groups: dict[tuple[str, str], Row] = {}
    for source in table.sources:
        only = set(source.get("methods", []))
        rename = source.get("as")
        for path in discover_runs([ROOT / source["path"]]):
            run = load_run(path)
            if (only and run.method not in only) or (source.get("programs") is not None
                                                     and run.program not in source["programs"]):
                continue
            method = rename or run.method
            # A run started from a copy of the task's own program file is tabulated as the task's own.
            program = source.get("as_program", run.program)
            key = (method, program, run.seed)
            rel = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
            if key in seen:
                notes.append(f"`{rel}` repeats {method} seed {run.seed} of `{seen[key]}`: left out")
                continue
            if run.final_step < min(table.budgets):
                notes.append(f"`{rel}` stopped at {run.final_step:,} steps: left out")
                continue
            if run.final_step < max(table.budgets):
                reached = [_k(b) for b in table.budgets if b <= run.final_step]
                notes.append(f"`{rel}` stopped at {run.final_step:,} steps: in the {', '.join(reached)} "
                             f"column{'s' if len(reached) > 1 else ''} only")
            seen[key] = rel
            saved = read_json(path / "config.json") or {}
            env, cfg = saved.get("environment", {}), saved.get("config", {})
            row = groups.setdefault((method, program), Row(method, program, [], [], [], []))
            row.runs.append(run)
            recorded = env.get("source")
            commit = (f"`{recorded[:7]}`" if recorded else
                      f"`{source['commit']}` (bench log: the runs predate recording it)"
                      if "commit" in source else "not recorded")
            for resumed in saved.get("resumed_elsewhere") or []:  # continued on other code or hardware
                later = str((resumed.get("environment") or {}).get("source") or "?")
                commit += f", resumed from {_k(int(resumed.get('step', 0)))} at `{later[:7]}`"
            row.commits.append(commit)
            row.cpus.append(str(env.get("cpu") or "not recorded"))
            row.settings.append(f"agent lr {cfg.get('agent', {}).get('lr')}, evaluation every "
                                f"{cfg.get('eval_every'):,} steps on {cfg.get('eval_episodes')} episodes")
    order = order_methods(m for m, _ in groups) if not table.methods else table.methods
    rows = sorted(groups.values(), key=lambda r: (order.index(r.method) if r.method in order else len(order),
                                                  r.program))
    for r in rows:
        r.runs.sort(key=lambda run: run.seed)
    return rows, notes


def curve_until(run: RunRecord, budget: int) -> tuple[list[int], list[float]]:
    """The run's evaluation steps and returns at or before ``budget`` (a longer run read at a smaller one)."""
    rows = [(s, v) for s, v in zip(run.eval_steps, run.eval_returns, strict=True) if s <= budget]
    return [s for s, _ in rows], [v for _, v in rows]


def final_return(run: RunRecord, budget: int) -> float:
    """Mean evaluation return over the final 10% of ``budget``, from the rows at or before it."""
    return M.asymptotic_performance(*curve_until(run, budget), budget)


def spread(values: Sequence[float]) -> str:
    if len(values) == 1:
        return fmt_return(values[0])
    if len(values) < MIN_SEEDS_FOR_CI:  # mean [min, max]: no interval to bootstrap
        return spread_text(list(values), math.nan, math.nan, math.nan)
    point, low, high = M.stratified_bootstrap_ci([list(values)], reps=20_000, seed=0)
    return spread_text(list(values), point, low, high)


def reaching(runs: Sequence[RunRecord], budget: int) -> list[RunRecord]:
    """The runs that trained for at least ``budget`` steps (a table's smaller budgets take shorter runs)."""
    return [run for run in runs if run.final_step >= budget]


def budget_cell(row: Row, budget: int) -> str:
    """The final return at ``budget`` over the row's runs that reached it, naming them when not all did."""
    runs = reaching(row.runs, budget)
    if not runs:
        return f"not run to {_k(budget)}"
    text = spread([final_return(x, budget) for x in runs])
    return text if len(runs) == len(row.runs) else f"{text} (seeds {', '.join(str(x.seed) for x in runs)})"


def posture_cell(row: Row, feature: str, budget: int) -> str:
    """The feature's mean over each run's final evaluation episodes (``posture.json``), over the seeds
    that ran to ``budget``."""
    values = []
    runs = reaching(row.runs, budget)
    if not runs:
        return f"not run to {_k(budget)}"
    for run in runs:
        saved = read_json(run.path / "posture.json") or {}
        value = saved.get("features", {}).get(feature, {}).get("mean")
        if isinstance(value, int | float):
            values.append(float(value))
    if not values:
        return "not recorded"
    text = (f"{values[0]:.2f}" if len(values) == 1 else
            f"mean {sum(values) / len(values):.2f} [{min(values):.2f}, {max(values):.2f}]")
    return text if len(values) == len(runs) else f"{text} ({len(values)} of {len(runs)} seeds)"


def escapes_cell(row: Row, budget: int) -> str:
    """Per seed (in the seeds column's order), the escapes the monitor's plateau detector installed up to
    ``budget`` and how many of them their probation kept: "kept/installed"; "—" for a run without an
    outer loop (once for a row of such runs). An escape still on probation at ``budget`` counts as
    installed, not kept."""
    runs = reaching(row.runs, budget)
    if not runs:
        return f"not run to {_k(budget)}"
    cells = []
    for run in runs:
        folder = run.path / "interventions"
        if not folder.is_dir():
            cells.append("—")
            continue
        installed = kept = 0
        for edit in sorted(folder.iterdir()):
            evidence = read_json(edit / "evidence.json") or {}
            decision = read_json(edit / "decision.json") or {}
            if evidence.get("cause") != "plateau" or not decision.get("accepted"):
                continue
            if int(evidence.get("step", 0)) > budget:
                continue
            installed += 1
            verdict = read_json(edit / "probation.json") or {}
            kept += bool(verdict.get("kept")) and int(verdict.get("step", 0)) <= budget
        cells.append(f"{kept}/{installed}")
    return "—" if set(cells) == {"—"} else ", ".join(cells)


def efficiency(rows: list[Row], row: Row, budget: int) -> str:
    oracle = [final_return(r, budget) for o in rows if o.method == "dense" and o.program == row.program
              for r in reaching(o.runs, budget)]
    if not oracle:
        return "n/a"
    threshold = M.oracle_threshold(sum(oracle) / len(oracle))
    runs = reaching(row.runs, budget)
    if not runs:
        return f"not run to {_k(budget)}"
    reached = [step for run in runs
               if (step := M.sample_efficiency(*curve_until(run, budget), threshold)) is not None]
    if not reached:
        return "—"
    text = f"{sum(reached) / len(reached) / 1e3:.0f}k"
    return text if len(reached) == len(runs) else f"{text} ({len(reached)}/{len(runs)})"


# --------------------------------------------------------------------------------------- writing
def _k(budget: int) -> str:
    return f"{budget // 1000}k" if budget % 1000 == 0 else f"{budget:,}"


def title_of(table: Table, method: str) -> str:
    return table.titles.get(method) or METHOD_TITLES.get(method, method)


def render_table(table: Table, rows: list[Row]) -> str:
    """One row per method; with several initial programs, one column per program at the last budget."""
    programs = list(dict.fromkeys(r.program for r in rows))
    last = table.budgets[-1]
    if len(programs) > 1:
        methods = list(dict.fromkeys(r.method for r in rows))
        body = []
        for p in programs:
            cells = []
            for m in methods:
                match = [r for r in rows if r.method == m and r.program == p]
                cells.append(f"{spread([final_return(x, last) for x in match[0].runs])} ({len(match[0].runs)})"
                             if match else "")
            body.append([f"`{p}`" if p else "the task's own program", *cells])
        return md_table(["Initial program", *[title_of(table, m) for m in methods]], body)
    header = ["Method", "seeds", *[f"final return, {_k(b)}" for b in table.budgets],
              f"steps to 50% of dense ({_k(last)})"]
    if table.posture:
        header.append(f"{table.posture} at {_k(last)} (final evaluation episodes)")
    if table.escapes:
        header.append(f"escapes kept/installed by {_k(last)}, per seed")
    if table.paper:
        header.append(f"paper ({table.paper_ref})" if table.paper_ref else "paper")
    body = []
    for r in rows:
        cells = [title_of(table, r.method), ", ".join(str(x.seed) for x in r.runs)]
        cells += [budget_cell(r, b) for b in table.budgets]
        cells.append(efficiency(rows, r, last))
        if table.posture:
            cells.append(posture_cell(r, table.posture, last))
        if table.escapes:
            cells.append(escapes_cell(r, last))
        if table.paper:
            paper = table.paper.get(r.method, "")
            cells.append(f"{paper:,}" if isinstance(paper, int | float) else str(paper))
        body.append(cells)
    # The paper's rows that no run here answers yet: listed, so that a gap shows where it is.
    for method in order_methods(m for m in table.paper if m not in {r.method for r in rows}):
        cells = [title_of(table, method), "not run yet", *["—" for _ in table.budgets], "—"]
        if table.posture:
            cells.append("—")
        if table.escapes:
            cells.append("—")
        paper = table.paper[method]
        cells.append(f"{paper:,}" if isinstance(paper, int | float) else str(paper))
        body.append(cells)
    return md_table(header, body)


def provenance(rows: list[Row]) -> str:
    commits: dict[str, list[str]] = {}
    cpus: set[str] = set()
    for r in rows:
        for c in sorted(set(r.commits)):
            commits.setdefault(c, [])
            if r.method not in commits[c]:
                commits[c].append(r.method)
        cpus.update(r.cpus)
    settings = sorted({s for r in rows for s in r.settings})
    made = "; ".join(f"{c}: {', '.join(ms)}" for c, ms in commits.items())
    return (f"Commits: {made}. CPU: {', '.join(sorted(cpus))}. Settings: {'; '.join(settings)}.")


def plot(table: Table, rows: list[Row], path: Path) -> None:
    last = table.budgets[-1]
    panels: dict[str, dict[str, list[Curve]]] = {}
    for r in rows:
        curves = [Curve(*curve_until(x, last)) for x in r.runs]
        panels.setdefault(r.program or r.runs[0].task_title, {})[r.method] = curves
    methods = list(dict.fromkeys(r.method for r in rows))
    plot_learning_curves(panels, path, title=table.title, panel_titles={p: p for p in panels},
                         method_titles={m: title_of(table, m) for m in methods}, methods=methods)


def render_pairs(pairs: Pairs) -> list[str]:
    """One row per parent checkpoint: each arm's final return (mean over its fork seeds) and each arm's
    difference from the control in the same row; the last row: the means over parents."""
    arms = {stem: [] for stem, _ in pairs.arms}
    found: dict[tuple[str, int], dict[str, list[RunRecord]]] = {}
    cpus, commits = set(), set()
    for path in discover_runs([ROOT / pairs.source]):
        saved = read_json(path / "config.json") or {}
        fork = saved.get("forked_from") or {}
        program = [re.sub(r"_s\d+$", "", Path(fork["program_file"]).stem)] if fork.get("program_file") else []
        stem = "+".join([*program, *(fork.get("settings") or [])])
        if not fork or stem not in arms:
            continue
        run = load_run(path)
        if run.final_step < run.steps:  # still training, or stopped: its final window is not there yet
            continue
        parent = (f"{fork.get('method')} seed {fork.get('seed')}", int(fork.get("step", 0)))
        found.setdefault(parent, {}).setdefault(stem, []).append(run)
        cpus.add(str((saved.get("environment") or {}).get("cpu")))
        commits.add(str((saved.get("environment") or {}).get("source"))[:7])
    titles = [t for _, t in pairs.arms]
    header = ["Parent (checkpoint)", "fork seeds", *titles, *[f"{t} vs control" for t in titles[1:]]]
    body, deltas = [], {stem: [] for stem, _ in pairs.arms[1:]}
    for (parent, step), by_arm in sorted(found.items()):
        finals = {stem: [final_return(r, r.steps) for r in by_arm.get(stem, [])] for stem in arms}
        for stem in arms:
            if finals[""]:  # the means compare arms over the same parents: those with a control
                arms[stem].extend(finals[stem])
        control = sum(finals[""]) / len(finals[""]) if finals[""] else math.nan
        cells = [f"{parent} at {_k(step)}", ", ".join(sorted({str(r.seed) for rs in by_arm.values() for r in rs}))]
        cells += [fmt_return(sum(v) / len(v)) if v else "—" for v in finals.values()]
        for stem, _ in pairs.arms[1:]:
            if finals[stem] and math.isfinite(control):
                d = (sum(finals[stem]) / len(finals[stem]) - control) / abs(control)
                deltas[stem].append(d)
                cells.append(f"{100 * d:+.1f}%")
            else:
                cells.append("—")
        body.append(cells)
    if body:
        paired = sum(1 for by_arm in found.values() if by_arm.get(""))
        cells = [f"over the {paired} parent{'s' if paired != 1 else ''} with a control", ""]
        cells += [spread(v) if v else "—" for v in arms.values()]
        cells += [(f"{100 * sum(d) / len(d):+.1f}% [{100 * min(d):+.1f}%, {100 * max(d):+.1f}%]" if d else "—")
                  for d in deltas.values()]
        body.append(cells)
    out = [f"## {pairs.title}", "", pairs.question, "",
           "Cells: final return (mean evaluation return over the final 10% of each fork's budget), and each arm "
           "against the control forked from the same checkpoint with the same seed.", "",
           md_table(header, body).rstrip("\n") if body else "No runs archived yet.", ""]
    if pairs.text:
        out += [pairs.text, ""]
    out += [f"Made by: `{pairs.command}`", "",
            f"Commits: {', '.join(f'`{c}`' for c in sorted(commits))}. CPU: {', '.join(sorted(cpus))}." if body
            else "", ""]
    return out


def speed_block(page: Path) -> str:
    """The throughput table ``bench/throughput.py`` last wrote into the page, markers included."""
    text = page.read_text(encoding="utf-8") if page.exists() else ""
    if SPEED_BEGIN in text and SPEED_END in text:
        return text[text.index(SPEED_BEGIN): text.index(SPEED_END) + len(SPEED_END)]
    return f"{SPEED_BEGIN}\n(no measurement yet: python bench/throughput.py)\n{SPEED_END}"


def render(meta: dict[str, Any], tables: list[Table | Pairs], *, figures: Path | None, speed: str = "") -> str:
    out = [meta.get("intro", "# Results").strip(), ""]
    for table in tables:
        if isinstance(table, Pairs):
            out += render_pairs(table)
            continue
        rows, notes = collect(table)
        counts = [len(r.runs) for r in rows]
        wide = len({r.program for r in rows}) > 1
        what = f"final return at {_k(table.budgets[-1])} (seeds), " if wide else ""
        out += [f"## {table.title}", "", table.question, "", f"Cells: {what}{spread_label(counts or [0])}.", "",
                render_table(table, rows), ""]
        if figures is not None and rows:
            plot(table, rows, figures / f"{table.id}.png")
        if rows:
            out += [f"![{table.title}]({FIGURES}/{table.id}.png)", ""]
        if table.text:
            out += [table.text, ""]
        out += [f"Made by: `{table.command}`", "", provenance(rows) if rows else "No runs archived yet.", ""]
        if notes:
            out += [*[f"- {n}" for n in notes], ""]
    for key in ("decisions", "speed"):
        if key in meta:
            out += [meta[key].strip(), ""]
        if key == "speed" and speed:
            out += [speed, ""]
    return "\n".join(out).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--spec", type=Path, default=SPEC)
    parser.add_argument("--page", type=Path, default=PAGE)
    parser.add_argument("--check", action="store_true", help="compare, write nothing; exit 1 if it differs")
    args = parser.parse_args(argv)
    meta, tables = load_spec(args.spec)
    speed = speed_block(args.page)
    if args.check:
        text = render(meta, tables, figures=None, speed=speed)
        current = args.page.read_text(encoding="utf-8") if args.page.exists() else ""
        if current != text:
            print(f"{args.page} is not what {args.spec} and the archived runs give: run "
                  "python bench/results_page.py", file=sys.stderr)
            return 1
        return 0
    figures = args.page.parent / FIGURES
    figures.mkdir(parents=True, exist_ok=True)
    text = render(meta, tables, figures=figures, speed=speed)
    args.page.write_text(text, encoding="utf-8")
    drawn = sum(1 for table in tables if (figures / f"{table.id}.png").exists())
    print(f"wrote {args.page} ({len(text.splitlines())} lines) and {drawn} figures in {figures}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

