"""Keep the small, auditable part of benchmark runs in git, so that a table can be rebuilt (and a grid
filled over several sittings) after the run directories themselves are gone.

Run directories (``bench/runs/``) hold checkpoints and replay buffers and stay out of git. This copies,
for every run under each ``OUT`` given, the files a table and an audit need — ``eval.csv`` (the curve
every table is read from), ``config.json`` (what ran), ``status.json``, ``diagnostics.csv`` (the
monitor's and the structural check's readings, one row per cycle), the factor programs and each
intervention's decision, evidence and (where a reply was sent back) attempts, and the LLM exchanges
(``llm/exchanges.jsonl``: every prompt and reply, replayable with ``mira llm export``) — to
``bench/archive/<OUT's name>/``, keeping the layout, so that

    mira report bench/archive/hc100_sac_ircr --out report
    python bench/results_page.py          # the tables of docs/results.md, from bench/results.toml

read the archive as they read the runs. A run still training is copied as far as it got; copying again
refreshes it.

    python bench/archive.py bench/runs/hc100 --as hc100_sac_dense   # the folder named by what it holds
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARCHIVE = ROOT / "bench" / "archive"

KEPT = ("eval.csv", "config.json", "status.json", "decomposition.json", "diagnostics.csv", "plateau.csv",
        "posture.json", "llm/exchanges.jsonl")
"""Files of a run directory that are copied as they are."""
KEPT_GLOBS = ("programs/*.json", "interventions/*/decision.json", "interventions/*/evidence.json",
              "interventions/*/attempts.json", "interventions/*/probation.json", "interventions/*/accepted.diff")
"""Smaller trees of a run directory: its program versions and each intervention's record."""


def run_dirs(out: Path) -> list[Path]:
    """Every run directory under ``out`` (a directory holding ``config.json``), at any depth."""
    return sorted(p.parent for p in out.rglob("config.json") if (p.parent / "eval.csv").exists())


def archive(out: Path, dest_root: Path = ARCHIVE, name: str | None = None) -> list[Path]:
    """Copy the kept files of every run under ``out`` to ``dest_root/<name or out.name>/``; returns the runs
    copied."""
    if not out.is_dir():
        raise SystemExit(f"archive: {out} is not a directory of runs")
    copied = []
    for run in run_dirs(out):
        dest = dest_root / (name or out.name) / run.relative_to(out)
        files = [run / name for name in KEPT if (run / name).exists()]
        files += [p for pattern in KEPT_GLOBS for p in sorted(run.glob(pattern))]
        for src in files:
            target = dest / src.relative_to(run)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, target)
        copied.append(run)
    return copied


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("outs", nargs="+", type=Path, help="benchmark output directories (e.g. bench/runs/hc100)")
    ap.add_argument("--dest", type=Path, default=ARCHIVE, help="archive root (default: bench/archive)")
    ap.add_argument("--as", dest="name", default=None,
                    help="the archive folder's name, saying what it holds (default: OUT's name; one OUT only)")
    args = ap.parse_args()
    if args.name and len(args.outs) > 1:
        ap.error("--as names one archive folder: give one OUT")
    for out in args.outs:
        runs = archive(out, args.dest, args.name)
        print(f"archive: {len(runs)} runs of {out} -> {args.dest / (args.name or out.name)}")


if __name__ == "__main__":
    main()
