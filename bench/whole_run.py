"""Whole-run cost of each reward method over `sparse`, with the same budget:
``python bench/whole_run.py [--methods sparse,hars,mira] [--steps 50000] [--repeats 2]``.

Runs ``mira train`` once per method and repeat, one run at a time, methods alternated within each
repeat so that a machine whose speed drifts hits them alike, with every setting but ``--method``
equal (learning starts, evaluation schedule, seed, one PyTorch thread by default). The figure is the
run's own wall time at its final evaluation (``eval.csv``'s ``wall_s``: environment steps, updates,
evaluations, checkpoints, MIRA's monitor cycles and interventions, everything the run did), compared
with the `sparse` run of the same repeat. For `mira` it also counts the interventions and the
accepted program edits from the run directory. Unlike ``throughput.py`` (a few thousand steps on a
small buffer), this is the cost over a budget users run, with the replay buffer growing to its size.

A measurement script, not a test; the table goes to stdout (docs/results.md holds the current figures).
"""

from __future__ import annotations

import argparse
import csv
import json
import shlex
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def interventions(run: Path) -> tuple[int, int]:
    """(interventions, accepted edits) recorded in a run directory."""
    folders = sorted((run / "interventions").glob("*/decision.json"))
    accepted = sum(bool(json.loads(p.read_text()).get("accepted")) for p in folders)
    return len(folders), accepted


def final_wall_s(run: Path) -> float:
    with open(run / "eval.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return float(rows[-1]["wall_s"])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--methods", default="sparse,hars,mira")
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--algo", default="sac")
    p.add_argument("--steps", type=int, default=50_000)
    p.add_argument("--learning-starts", type=int, default=10_000)
    p.add_argument("--eval-every", type=int, default=10_000)
    p.add_argument("--eval-episodes", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--train-args", default="", help="extra flags for every mira train run")
    p.add_argument("--out", type=Path, default=ROOT / "bench" / "runs" / "whole_run")
    args = p.parse_args(argv)
    methods = args.methods.split(",")
    if "sparse" not in methods:
        p.error("--methods must include sparse (the reference)")

    walls: dict[str, list[float]] = {m: [] for m in methods}
    edits: dict[str, list[tuple[int, int]]] = {m: [] for m in methods}
    for repeat in range(args.repeats):
        for method in methods:
            run = args.out / f"{method}-r{repeat}"
            cmd = [sys.executable, "-m", "mira.cli", "train", "--task", args.task, "--method", method,
                   "--algo", args.algo, "--steps", str(args.steps), "--learning-starts", str(args.learning_starts),
                   "--eval-every", str(args.eval_every), "--eval-episodes", str(args.eval_episodes),
                   "--seed", str(args.seed), "--threads", str(args.threads), "--quiet", "--overwrite",
                   "--out", str(run), *shlex.split(args.train_args)]
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            walls[method].append(final_wall_s(run))
            edits[method].append(interventions(run))
            print(f"[{repeat + 1}/{args.repeats}] {method:8s} {walls[method][-1]:8.1f} s", flush=True)

    print(f"\n{args.task}, {args.algo}, {args.steps} steps (learning starts {args.learning_starts}, evaluation every "
          f"{args.eval_every} x {args.eval_episodes} episodes), seed {args.seed}, {args.threads} thread(s), "
          f"{args.repeats} repeat(s), methods alternated\n")
    print("| method | wall s per run | vs sparse (per repeat) | interventions (accepted) |")
    print("|---|---|---|---|")
    for method in methods:
        ratios = [w / s for w, s in zip(walls[method], walls["sparse"], strict=True)]
        vs = "—" if method == "sparse" else (f"{100 * (statistics.median(ratios) - 1):+.1f}% (" +
                                              ", ".join(f"{100 * (r - 1):+.1f}%" for r in ratios) + ")")
        inter = "—" if method != "mira" and not any(n for n, _ in edits[method]) else \
            ", ".join(f"{n} ({a})" for n, a in edits[method])
        runs = ", ".join(f"{w:.1f}" for w in walls[method])
        print(f"| {method} | {statistics.median(walls[method]):.1f} ({runs}) | {vs} | {inter} |")


if __name__ == "__main__":
    main()
