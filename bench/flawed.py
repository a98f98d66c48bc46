"""Flawed-program benchmark: does MIRA repair, during training, an initial reward program that is wrong?

Every program of ``bench/flawed/flaws.toml`` (for the task) is the initial program of ``hars`` (static
program), ``mira``, ``mira-no-mcm`` and ``mira-no-srr``; the task's own program (``good``) runs with
``hars`` and ``mira``. Each run is a real ``mira train --program FILE`` subprocess
(:func:`learning.run_ours`), in ``<out>/<task>/<flaw>/<method>-<algo>-s<seed>``; a rerun resumes or
extends the runs already there.

    python bench/flawed.py --task halfcheetah --seeds 0,1,2 --steps 100000 --workers 2
    python bench/flawed.py --task halfcheetah --flaws no_progress,abs_velocity --methods hars,mira --seeds 0
    python bench/flawed.py --task humanoidstandup --good-only --methods mira --seeds 0   # the good program only
    python bench/flawed.py --task halfcheetah --table-only --steps 100000
    python bench/flawed.py --task halfcheetah --table-only --steps 50000 --out bench/runs/new \
        --from bench/archive/flawed_s1,bench/archive/flawed_h      # new runs beside archived ones
    python bench/flawed.py --programs bench/flawed_heldout --task halfcheetah --methods hars,mira --seeds 0 \
        --steps 50000 --skip-good --out bench/runs/flawed_heldout   # the held-out set of flawed programs

``bench/flawed_heldout`` is a second set, written after the offline engineer's rules were fixed, with
factor names and forms the rules have never met: a check that the repairs come from the evidence and
not from recognising the first set's programs.

The table gives, per flaw and method, the final return (IQM over seeds with a 95% bootstrap CI, as in
``bench/learning.py``) and its ratio to good-program ``hars``; then the issue's targets, and each
``mira`` run's interventions (step, what the evidence named, the edit, accepted or not). Results go to
``bench/RESULTS.md`` under "Repairing flawed programs".
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import tomllib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from learning import final_return, run_ours, run_sources  # type: ignore[import-not-found]
from mira.cli import cpu_model
from mira.experiments.metrics import stratified_bootstrap_ci
from mira.explain import interventions as explain_interventions
from mira.runio.csvlog import read_csv

ROOT = Path(__file__).resolve().parents[1]
FLAWED = ROOT / "bench" / "flawed"
GOOD = "good"


def flaws(task: str, programs: Path = FLAWED) -> list[dict[str, str]]:
    """The task's entries of ``<programs>/flaws.toml`` (name, kind, flaw)."""
    entries = tomllib.loads((programs / "flaws.toml").read_text(encoding="utf-8"))["flaw"]
    return [e for e in entries if e["task"] == task]


def jobs(task: str, names: list[str], methods: list[str], seeds: list[int],
         good: bool = True) -> list[tuple[str, str, int]]:
    """(flaw, method, seed), seed-major; the good program (unless ``good`` is False) gets ``hars`` and
    ``mira`` only."""
    out = []
    for seed in seeds:
        for name in [GOOD, *names] if good else names:
            for method in methods:
                if name == GOOD and method not in ("hars", "mira"):
                    continue
                out.append((name, method, seed))
    return out


def runs(roots: list[Path], name: str, method: str, algo: str,
         reference: dict[int, Path] | None = None) -> dict[int, Path]:
    """seed → run directory of ``method`` on program ``name``, gathered over ``roots`` (each a
    ``<out>/<task>``); where two roots hold the same seed, the earlier root's run is the one read.
    ``reference`` (see :func:`reference_runs`) fills the good program's ``hars`` seeds the roots lack."""
    found: dict[int, Path] = {}
    for root in roots:
        for run in sorted((root / name).glob(f"{method}-{algo}-s*")):
            if (run / "eval.csv").is_file():
                found.setdefault(int(run.name.rpartition("-s")[2]), run)
    if name == GOOD and method == "hars":
        for seed, run in (reference or {}).items():
            found.setdefault(seed, run)
    return dict(sorted(found.items()))


def reference_runs(task: str, algo: str, dirs: list[Path]) -> dict[int, Path]:
    """seed → run directory, for runs made elsewhere that stand for good-program ``hars``: runs of the
    task's own program (no ``--program``) by ``hars``, or by a ``mira`` method that installed no program
    (until an edit its agent is ``hars``'s bit for bit), e.g. ``bench/learning.py``'s. Anything else is
    refused with the reason."""
    out: dict[int, Path] = {}
    for run in dirs:
        try:
            cfg = json.loads((run / "config.json").read_text(encoding="utf-8"))["config"]
        except (OSError, ValueError, KeyError) as exc:
            raise ValueError(f"{run}: no readable config.json ({exc})") from None
        accepted = [d.parent.name for d in sorted(run.glob("interventions/*/decision.json"))
                    if json.loads(d.read_text(encoding="utf-8")).get("accepted")]
        problems = [why for bad, why in [
            (cfg.get("task") != task, f"task {cfg.get('task')!r}, not {task!r}"),
            (cfg.get("algo") != algo, f"algo {cfg.get('algo')!r}, not {algo!r}"),
            (bool(cfg.get("program")), f"started from {cfg.get('program')}, not the task's own program"),
            (cfg.get("method") != "hars" and not str(cfg.get("method")).startswith("mira"),
             f"method {cfg.get('method')!r} is neither hars nor mira"),
            (bool(accepted), f"installed a program ({', '.join(accepted)}), so its agent is not hars's"),
            (not (run / "eval.csv").is_file(), "no eval.csv")] if bad]
        if problems:
            raise ValueError(f"{run}: " + "; ".join(problems))
        out.setdefault(int(cfg["seed"]), run)
    return out


def finals(roots: list[Path], name: str, method: str, algo: str, budget: int,
           reference: dict[int, Path] | None = None) -> dict[int, float]:
    """seed → final return of the finished-enough runs of ``method`` on program ``name``."""
    out = {}
    for seed, run in runs(roots, name, method, algo, reference).items():
        curve = [(int(r["step"]), float(r["return_mean"])) for r in read_csv(run / "eval.csv")]
        value = final_return(curve, budget)
        if value is not None:
            out[seed] = value
    return out


def iqm(values: list[float]) -> tuple[float, float, float]:
    return stratified_bootstrap_ci([values]) if values else (float("nan"),) * 3  # type: ignore[return-value]


def interventions(run: Path) -> list[str]:
    """One line per intervention of a run (:func:`mira.explain.interventions`): step, the edit, the
    decision, and why it happened."""
    return [f"{i.step}: {i.edit if i.accepted else 'nothing installed'}, "
            f"{f'installed v{i.version}' if i.accepted else 'backed off'} ({i.why})"
            for i in explain_interventions(run)]


def table(roots: list[Path], task: str, algo: str, budget: int, methods: list[str], header: list[str],
          reference: dict[int, Path] | None = None, programs: Path = FLAWED) -> str:
    """The issue's table over the runs under ``roots`` (each a ``<out>/<task>``, earlier roots first) of
    the programs listed in ``<programs>/flaws.toml``."""
    entries = {e["name"]: e for e in flaws(task, programs)}
    good = iqm(list(finals(roots, GOOD, "hars", algo, budget, reference).values()))[0]
    lines = [*header, "", f"Reference: good-program `hars` {good:.0f} (the ratios below are to it).", "",
             "| program | kind | " + " | ".join(methods) + " |", "|---|---|" + "---|" * len(methods)]
    ratios: dict[tuple[str, str], float] = {}
    for name in [GOOD, *entries]:
        if not any((root / name).is_dir() for root in roots):
            continue
        cells = []
        for method in methods:
            per_seed = finals(roots, name, method, algo, budget, reference)
            if not per_seed:
                cells.append("-")
                continue
            point, lo, hi = iqm(list(per_seed.values()))
            ratios[name, method] = point / good if good and np.isfinite(good) else float("nan")
            shown = round(ratios[name, method], 2) + 0.0  # a ratio that rounds to zero reads "0%", not "-0%"
            cells.append(f"{point:.0f} [{lo:.0f}, {hi:.0f}] ({shown:.0%}, {len(per_seed)} s)")
        kind = "-" if name == GOOD else entries[name]["kind"]
        lines.append(f"| {name} | {kind} | " + " | ".join(cells) + " |")
    structural = [n for n, e in entries.items() if e["kind"] == "structural"]
    parametric = [n for n, e in entries.items() if e["kind"] == "parametric"]
    repaired = [n for n in structural if ratios.get((n, "mira"), 0) >= 0.7 and ratios.get((n, "hars"), 1) < 0.5]
    absorbed = [n for n in parametric if min(ratios.get((n, "hars"), 0), ratios.get((n, "mira"), 0)) >= 0.7]

    # The ablation ordering compares means, so every method's mean is taken over the same flaws: those
    # that all of ``methods`` have run.
    shared = [n for n in structural if all((n, m) in ratios for m in methods)]

    def mean_ratio(method: str) -> float:
        return float(np.mean([ratios[n, method] for n in shared])) if shared else float("nan")

    def not_run(names: list[str]) -> str:
        # A row without both `hars` and `mira` can neither meet nor miss a target: it is named, not counted.
        missing = [n for n in names if (n, "hars") not in ratios or (n, "mira") not in ratios]
        return f"; not run with both `hars` and `mira`: {', '.join(missing)}" if missing else ""

    good_line = (f"`mira` {ratios[GOOD, 'mira']:.0%} of `hars`" if (GOOD, "mira") in ratios
                 else "`mira` not run")
    lines += ["", f"* Structural flaws repaired (`mira` ≥ 70%, `hars` < 50%): {len(repaired)} of {len(structural)} "
              f"({', '.join(repaired) or 'none'}{not_run(structural)}); target: at least 3 of 4.",
              f"* Parametric flaws absorbed (`hars` and `mira` ≥ 70%): {len(absorbed)} of {len(parametric)} "
              f"({', '.join(absorbed) or 'none'}{not_run(parametric)}).",
              f"* Mean ratio over the structural flaws every method ran ({', '.join(shared) or 'none'}): "
              + ", ".join(f"`{m}` {mean_ratio(m):.0%}" for m in methods) + ".",
              f"* Good program: {good_line}."]
    stories = []
    for name in [GOOD, *entries]:
        for seed, run in runs(roots, name, "mira", algo).items():
            stories += [f"  * {name} s{seed}: step {line}" for line in interventions(run)]
    if stories:
        lines += ["", "Interventions of the `mira` runs:", *stories]
    return "\n".join(lines)


def plot(roots: list[Path], task: str, algo: str, methods: list[str],
         reference: dict[int, Path] | None = None, programs: Path = FLAWED) -> Path | None:
    """One panel per program: each method's mean evaluation curve over seeds, and a tick at every step
    where a ``mira`` run installed a new program (``curves.png`` in the first root)."""
    from matplotlib.ticker import FuncFormatter

    from mira.experiments.plots import Curve, _figure, band, method_colour, steps_label

    names = [n for n in [GOOD, *(e["name"] for e in flaws(task, programs))]
             if any((r / n).is_dir() for r in roots)]
    if not names:
        return None
    fig, canvas = _figure(5.0 * min(len(names), 3), 3.4 * ((len(names) + 2) // 3))
    for k, name in enumerate(names):
        ax = fig.add_subplot((len(names) + 2) // 3, min(len(names), 3), k + 1)
        drawn: list[tuple[str, list[float], list[float]]] = []
        for i, method in enumerate(methods):
            curves = [Curve([float(r["step"]) for r in rows], [float(r["return_mean"]) for r in rows])
                      for rows in (read_csv(run / "eval.csv")
                                   for run in runs(roots, name, method, algo, reference).values())
                      if rows]
            if not curves:
                continue
            steps, mean, _, count = band(curves)
            # A method whose runs repeat an earlier one's (``mira`` with no edit, ``mira-no-srr``) would
            # hide that curve: draw it dashed on top and say whose curve it is.
            same = next((m for m, s, y in drawn if list(s) == list(steps) and list(y) == list(mean)), None)
            label = f"{method} ({max(count)} s)" + (f" = {same}" if same else "")
            ax.plot(steps, mean, color=method_colour(method, i), lw=1.6, ls="--" if same else "-", label=label)
            drawn.append((method, list(steps), list(mean)))
        for decision in sorted(d for run in runs(roots, name, "mira", algo).values()
                               for d in run.glob("interventions/*/decision.json")):
            if json.loads(decision.read_text()).get("accepted"):
                step = float(decision.parent.name.rpartition("-step")[2])
                ax.axvline(step, color="#2ca02c", lw=0.8, ls="--")
        ax.set_title(name, fontsize=10)
        ax.xaxis.set_major_formatter(FuncFormatter(steps_label))
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, frameon=False)
    fig.suptitle(f"{task}: evaluation return from flawed initial programs (green lines: mira installed a program; "
                 "a dashed curve repeats the one its label names)")
    fig.tight_layout()
    roots[0].mkdir(parents=True, exist_ok=True)
    path = roots[0] / "curves.png"
    canvas.print_png(str(path))
    return path


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--programs", type=Path, default=FLAWED,
                   help="folder of flawed programs: flaws.toml and <task>/<name>.json (default bench/flawed; "
                        "bench/flawed_heldout holds a second set written after the engineer's rules)")
    p.add_argument("--flaws", default="", help="comma-separated flaw names (default: every flaw of the task)")
    p.add_argument("--methods", default="hars,mira,mira-no-mcm,mira-no-srr")
    p.add_argument("--algo", default="sac")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--steps", type=int, default=100_000)
    p.add_argument("--eval-every", type=int, default=5_000)
    p.add_argument("--eval-episodes", type=int, default=10)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "runs" / "flawed")
    p.add_argument("--train-args", default="", help="extra flags for mira train")
    p.add_argument("--table-only", action="store_true")
    p.add_argument("--from", dest="sources", default="",
                   help="comma-separated further run folders (each like --out) whose runs the table and plot "
                        "also read, e.g. archived ones; where two hold the same run, --out's (then the first "
                        "listed) is read")
    p.add_argument("--reference", default="",
                   help="comma-separated run directories that stand for good-program hars where the folders "
                        "hold no such seed: hars runs of the task's own program, or mira runs that installed "
                        "no program (e.g. bench/learning.py's); anything else is refused")
    p.add_argument("--good-only", action="store_true",
                   help="run only the good program (with the methods among hars and mira), no flawed one")
    p.add_argument("--skip-good", action="store_true",
                   help="run only the flawed programs (the good program's runs are the table's reference: "
                        "run them once, e.g. in another invocation)")
    args = p.parse_args()
    if not (args.programs / "flaws.toml").is_file():
        p.error(f"--programs: no flaws.toml in {args.programs}")
    known = [e["name"] for e in flaws(args.task, args.programs)]
    if args.good_only and (args.skip_good or args.flaws):
        p.error("--good-only runs no flawed program: it takes neither --skip-good nor --flaws")
    names = [] if args.good_only else [n for n in args.flaws.split(",") if n] or known
    unknown = sorted(set(names) - set(known))
    if unknown:
        p.error(f"unknown flaw(s) for {args.task}: {', '.join(unknown)} ({args.programs / 'flaws.toml'} has {known})")
    methods = args.methods.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    common = ["--eval-every", str(args.eval_every), "--eval-episodes", str(args.eval_episodes),
              *args.train_args.split()]
    if not args.table_only:
        with ProcessPoolExecutor(args.workers) as pool:
            futures = []
            for name, method, seed in jobs(args.task, names, methods, seeds, good=not args.skip_good):
                program = [] if name == GOOD else ["--program", str(args.programs / args.task / f"{name}.json")]
                futures.append(pool.submit(run_ours, method, args.algo, seed, args.steps, args.out / args.task / name,
                                           [*program, *common], args.task))
            for f in futures:
                f.result()
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    folders = [args.out, *(Path(d) for d in args.sources.split(",") if d)]
    roots = [d / args.task for d in folders]
    header = [f"{args.task}, {args.algo.upper()}, {args.steps} steps, seeds {args.seeds}, eval every {args.eval_every} "
              f"steps x {args.eval_episodes} episodes; figure = IQM over seeds of the mean eval return over the "
              "final 10% of the budget [95% CI] (ratio to good-program hars, seeds finished).",
              f"Machine: {cpu_model()}, {os.cpu_count()} cores, 1 torch thread per run, {args.workers} runs in "
              f"parallel; runs' code {run_sources(roots)}; table printed at {commit}; "
              f"extra train flags: {args.train_args or 'none'}.",
              "Runs read from: " + ", ".join(str(d) for d in folders) + "."]
    missing = [str(r) for r in roots[1:] if not r.is_dir()]
    if missing:
        p.error(f"--from: no runs of {args.task} under {', '.join(missing)}")
    try:
        reference = reference_runs(args.task, args.algo, [Path(d) for d in args.reference.split(",") if d])
    except ValueError as exc:
        p.error(f"--reference: {exc}")
    if reference:
        header.append("Good-program `hars` seeds read from elsewhere where the folders hold none: "
                      + ", ".join(f"s{seed} {run}" for seed, run in reference.items()) + ".")
    text = table(roots, args.task, args.algo, args.steps, methods, header, reference, args.programs)
    print(text)
    roots[0].mkdir(parents=True, exist_ok=True)
    (roots[0] / "table.md").write_text(text + "\n")
    figure = plot(roots, args.task, args.algo, methods, reference, args.programs)
    if figure is not None:
        print(f"curves: {figure}")


if __name__ == "__main__":
    main()
