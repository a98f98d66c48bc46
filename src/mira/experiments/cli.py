"""``mira sweep`` and ``mira report``: subcommand parsers for the main command line.

The main CLI registers them with ``add_sweep_parser(subparsers)`` and ``add_report_parser(subparsers)``;
each sets ``func(args) -> int``. Until then (and for tests) ``python -m mira.experiments.cli sweep|report``
runs them standalone.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

from mira.cli_types import nonneg_int as _nonneg_int
from mira.cli_types import positive_int as _positive_int
from mira.errors import MiraError, UsageError


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be positive, got {value}")
    return value


DRY_RUN_OUT = "OUT"
"""Where ``mira sweep --dry-run`` without ``--out`` shows the runs: a placeholder to replace."""


def add_sweep_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``sweep``: tasks × methods × algos × seeds as independent, resumable runs."""
    from mira.experiments.grid import PRESET_NOTES

    presets = "; ".join(f"{k}: {v}" for k, v in PRESET_NOTES.items())
    p: argparse.ArgumentParser = subparsers.add_parser(
        "sweep", help="run tasks × programs × methods × algos × seeds (local pool or Ray), resumably",
        description="Run every combination as its own `mira train` subprocess, each a run directory "
                    "OUT/<task>/<algo>/<method>/seed<k>. Rerunning the same command skips finished runs and "
                    "resumes interrupted ones. `tensorboard --logdir OUT` shows every run. "
                    f"Presets — {presets}",
    )
    p.add_argument("--tasks", default=None, help="comma-separated tasks (built-in names or task-card files)")
    p.add_argument("--programs", default=None,
                   help="comma-separated initial program files (mira train --program), one run each; 'task' "
                        "is the task's own program (the default: it alone). Runs from a file go to "
                        "OUT/<task>/<file stem>/<algo>/<method>/seed<k>")
    p.add_argument("--methods", default=None,
                   help="comma-separated methods, or 'all' (every registered method)")
    p.add_argument("--algos", default=None, help="comma-separated algos (sac, ddpg)")
    p.add_argument("--seeds", default=None,
                   help="a count K (seeds 0..K-1), a list 0,1,2 or a range 0-4 (a single seed S: 'S,'; "
                        "0 alone is seed 0)")
    p.add_argument("--steps", type=_positive_int, default=None, help="environment steps per run")
    p.add_argument("--out", default=None,
                   help="sweep output directory (required, except with --dry-run: there the runs are shown under "
                        f"{DRY_RUN_OUT}/ when it is not given)")
    p.add_argument("--workers", type=_positive_int, default=None,
                   help="runs in parallel on the local pool (default 1; the Ray backend starts a local "
                        "instance with this many CPUs when no --address is given)")
    p.add_argument("--backend", choices=("pool", "ray"), default=None, help="pool (default) or ray")
    p.add_argument("--address", default=None, help="Ray cluster address (e.g. auto, ray://head:10001)")
    p.add_argument("--cpus-per-run", type=_positive_float, default=None,
                   help="Ray: CPUs reserved per run (default 1)")
    p.add_argument("--retries", type=_nonneg_int, default=None,
                   help="re-attempts (resumes) of a failed run within this sweep (default 1)")
    p.add_argument("--preset", default=None, help="paper-small or paper (flags and --file override it)")
    p.add_argument("--file", default=None, help="sweep file (.toml, .yaml) with the grid and settings")
    p.add_argument("--train-args", default=None, metavar='"FLAGS"',
                   help='extra `mira train` flags for every run, e.g. "--eval-episodes 3 --hidden 64,64" '
                        '(a lone flag needs the = form: --train-args="--quiet")')
    p.add_argument("--dry-run", action="store_true",
                   help="print what each run would do and how long the sweep would take (from the speeds the runs "
                        "under --out logged), and exit at once")
    p.add_argument("--probe", action="store_true",
                   help="with --dry-run: also time a short run of each task/algo/method the runs under --out "
                        "have not measured (minutes)")
    p.add_argument("--no-probe", action="store_true", help=argparse.SUPPRESS)  # the default now; still accepted
    p.add_argument("--progress-every", type=_positive_int, default=30, help="seconds between progress lines")
    p.set_defaults(func=cmd_sweep)
    return p


def add_report_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``report``: Table 2/3-style tables, Figure 3–5-style plots, per-run MCM plots."""
    p: argparse.ArgumentParser = subparsers.add_parser(
        "report", help="tables and plots of runs or sweeps",
        description="Write report.md, table_<algo>.md/.csv, metrics.csv, aggregate.csv, runs.csv, "
                    "interventions.csv and PNG figures for every run directory found under the given paths. "
                    "Runs started from a program file (mira train --program) get a column and a curve "
                    "panel per file. Two runs of the same algorithm, task, program, method and seed: the one "
                    "under the path named first is tabulated, the other noted and left out.",
    )
    p.add_argument("paths", nargs="+", metavar="DIR", help="run directories and/or sweep directories")
    p.add_argument("--out", required=True, help="report directory")
    p.add_argument("--include-incomplete", action="store_true",
                   help="also tabulate runs that have not finished (their last evaluations so far)")
    p.add_argument("--bootstrap-reps", type=_positive_int, default=20_000, help="bootstrap replicates")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="bootstrap seed")
    p.add_argument("--no-plots", action="store_true", help="tables only")
    p.add_argument("--run-plots", choices=("all", "interventions", "none"), default="all",
                   help="runs that get a per-run diagnostics figure: all (default), only those with a "
                        "recorded intervention, or none (the curve figures are still drawn)")
    p.set_defaults(func=cmd_report)
    return p


def cmd_sweep(args: argparse.Namespace) -> int:
    from mira.experiments.grid import build_grid, parse_names, parse_programs, parse_seeds, split_train_args
    from mira.experiments.sweep import SweepOptions, dry_run, run_sweep

    overrides: dict[str, Any] = {
        "tasks": parse_names(args.tasks, "--tasks") if args.tasks else None,
        "programs": parse_programs(args.programs, "--programs") if args.programs else None,
        "methods": parse_names(args.methods, "--methods") if args.methods else None,
        "algos": parse_names(args.algos, "--algos") if args.algos else None,
        "seeds": parse_seeds(args.seeds, "--seeds") if args.seeds else None,
        "steps": args.steps,
        "train_args": (split_train_args(args.train_args, "--train-args")
                       if args.train_args is not None else None),
        "workers": args.workers, "backend": args.backend, "address": args.address,
        "cpus_per_run": args.cpus_per_run, "retries": args.retries,
    }
    if args.out is None and not args.dry_run:
        raise UsageError("--out DIR is required (only --dry-run can do without it)")
    grid, settings = build_grid(preset=args.preset, file=args.file, overrides=overrides)
    if args.dry_run:
        dry_run(grid, args.out or DRY_RUN_OUT, workers=settings.get("workers"), probe=args.probe and not args.no_probe)
        return 0
    options = SweepOptions(workers=settings.get("workers"), backend=settings.get("backend", "pool"),
                           address=settings.get("address"),
                           cpus_per_run=float(settings.get("cpus_per_run", 1)),
                           retries=int(settings.get("retries", 1)),
                           progress_every_s=float(args.progress_every))
    result = run_sweep(grid, args.out, options)
    print(f"sweep: {len(result.finished)} finished now, {len(result.skipped)} already finished, "
          f"{len(result.failed)} failed, {len(result.busy)} busy elsewhere in {result.wall_s:.0f} s; "
          f"report: mira report {result.out} --out {result.out}/report")
    for run_id, reason in result.failed.items():
        print(f"sweep: failed {run_id}: {reason}", file=sys.stderr)
    if result.interrupted:
        return 130
    return 0 if result.ok else 1


def cmd_report(args: argparse.Namespace) -> int:
    from mira.experiments.report import write_report

    result = write_report(args.paths, args.out, include_incomplete=args.include_incomplete,
                          bootstrap_reps=args.bootstrap_reps, seed=args.seed, plots=not args.no_plots,
                          run_plots=args.run_plots)
    used = sum(len(c.seeds) for c in result.cells)
    print(f"report: {used} runs tabulated ({len(result.runs)} found), {len(result.files)} files in "
          f"{result.out_dir} — see {result.out_dir / 'report.md'}")
    for note in result.notes:
        print(f"report: note: {note}")
    return 0


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """A standalone parser with just ``sweep`` and ``report`` (the main CLI adds them to its own)."""
    parser = _Parser(prog="mira", description="MIRA experiments: sweeps and reports")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    add_sweep_parser(sub)
    add_report_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except UsageError as exc:
        print(f"mira {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except MiraError as exc:
        print(f"mira {args.command}: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
